"""GNSS aiding: position (east, north) and velocity (east, north) of one receiver, and the freeze check.

    position  z = (e, n) of the fix in the local frame,  h(x) = (x, y),  H = H_POS
    velocity  z = (v_e, v_n),  h(x) = R(theta) (v_x, v_y),  H its Jacobian (gnss_velocity_model)
R is diagonal, from the receiver's own accuracy figures where it sends them (as EKF2 does), bounded
below by the configured floors and above by ACC_CAP times them (a receiver, or a spoofer, that
claims a huge error would otherwise blind every test):
    position  sigma = max(gnss_pos_sigma_m, gnss_pos_acc_fraction * h_acc): h_acc counts the slow,
              correlated error too, which the filter follows (q_pos_m); the innovation sees the
              epoch-to-epoch part, about 0.4 of it on u-blox receivers
    velocity  sigma = max(gnss_vel_sigma_mps, vel_acc): the speed accuracy is an epoch's noise
and where it sends none, gnss_vel_unreported_mps and, for the position, gnss_pos_unreported_m per
unit of the fix's HDOP where it gives one (an older receiver reports its geometry, not its accuracy:
at HDOP 1, 0.5 m; the Erle PXF's receivers flew at HDOP 1.3 to 2, their position wandering against
their own velocity by a metre), else gnss_pos_unreported_m (real receivers' levels, as EKF3's
defaults, not the simulator's).
"""

from __future__ import annotations

import math

import numpy as np

from guard.core.aiding import Aid
from guard.core.ekf import AX, AY, N_STATES, TH, VX, VY, X, Y, FilterConfig
from guard.model.events import Alarm
from guard.model.samples import GnssFix
from guard.model.sensors import Sensor

H_POS = np.zeros((2, N_STATES)); H_POS[0, X] = H_POS[1, Y] = 1.0


def gnss_velocity_model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h(x) = (v_e, v_n) = R(theta) (v_x, v_y), and its Jacobian."""
    th, vx, vy = x[TH], x[VX], x[VY]
    cs, sn = math.cos(th), math.sin(th)
    H = np.zeros((2, N_STATES))
    H[0, TH], H[0, VX], H[0, VY] = -vx * sn - vy * cs, cs, -sn
    H[1, TH], H[1, VX], H[1, VY] = vx * cs - vy * sn, sn, cs
    return np.array([vx * cs - vy * sn, vx * sn + vy * cs]), H


ACC_CAP = 10.0          # a reported accuracy counts up to this many times its floor
# a receiver that has just found a fix says it is good to tens of metres (47 m, then 22, 11, for its first
# 12 s on a real plane's u-blox with 5 satellites, HDOP 10.7), and its solution moves by metres as it
# converges: the filter starts on a fix the receiver itself calls good to this (as EKF3 checks its
# GPS before use), its HDOP where it reports no accuracy
START_H_ACC_M = 5.0
START_HDOP = 5.0


class GnssAiding:
    """Builds the GNSS measurements, R from each fix's accuracy figures (see the module's docstring)."""

    def __init__(self, f: FilterConfig):
        self.f = f

    def beyond_cap(self, fix: GnssFix) -> str | None:
        """What to say of a fix whose receiver calls itself worse than guard takes a receiver's word
        for (ACC_CAP times the floors; its HDOP, for one that reports no accuracy): its tests then
        assume the cap, and a receiver that poor may alarm where one that knows it is would not
        (None: nothing to say). The monitor says it once per filter."""
        f, parts = self.f, []
        cap_pos = ACC_CAP * f.gnss_pos_sigma_m
        if fix.h_acc_m and f.gnss_pos_acc_fraction * fix.h_acc_m > cap_pos:
            parts.append(f"its position good to {fix.h_acc_m:.1f} m only (guard takes up to "
                         f"{cap_pos / f.gnss_pos_acc_fraction:g} m)")
        elif not fix.h_acc_m and fix.hdop and f.gnss_pos_unreported_m * fix.hdop > cap_pos:
            parts.append(f"an HDOP of {fix.hdop:.1f} (guard takes up to {cap_pos / f.gnss_pos_unreported_m:g})")
        if f.use_gnss_velocity and fix.vel_acc_mps and fix.vel_acc_mps > ACC_CAP * f.gnss_vel_sigma_mps:
            parts.append(f"its velocity good to {fix.vel_acc_mps:.2f} m/s only (guard takes up to "
                         f"{ACC_CAP * f.gnss_vel_sigma_mps:g} m/s)")
        if not parts:
            return None
        return (f"the receiver reports {' and '.join(parts)}: guard tests it at those figures (a spoofer could "
                "claim any error to blind the tests), and a receiver this poor may raise alarms")

    def sigma_pos(self, fix: GnssFix) -> float:
        f = self.f
        if not fix.h_acc_m:
            if fix.hdop:            # no accuracy, but its geometry: gnss_pos_unreported_m per unit of HDOP
                return min(max(f.gnss_pos_sigma_m, f.gnss_pos_unreported_m * fix.hdop), ACC_CAP * f.gnss_pos_sigma_m)
            return f.gnss_pos_unreported_m
        return min(max(f.gnss_pos_sigma_m, f.gnss_pos_acc_fraction * fix.h_acc_m), ACC_CAP * f.gnss_pos_sigma_m)

    def too_coarse_to_start(self, fix: GnssFix) -> str | None:
        """What the receiver says of a fix too coarse to start the filter on (None: good enough)."""
        if fix.h_acc_m and fix.h_acc_m > START_H_ACC_M:
            return f"{fix.h_acc_m:.0f} m (its own accuracy)"
        if not fix.h_acc_m and fix.hdop and fix.hdop > START_HDOP:
            return f"HDOP {fix.hdop:.1f}"
        return None

    def q_pos(self, fix: GnssFix) -> float:
        """The position's random walk until this fix: q_pos_m, per unit of HDOP for a receiver read by
        its HDOP (its correlated error, ionosphere and multipath, grows with the geometry as its
        noise does)."""
        f = self.f
        if fix.h_acc_m or not fix.hdop:
            return f.q_pos_m
        return f.q_pos_m * min(max(fix.hdop, 1.0), ACC_CAP)

    def sigma_vel(self, fix: GnssFix) -> float:
        f = self.f
        if not fix.vel_acc_mps:
            return f.gnss_vel_unreported_mps
        return min(max(f.gnss_vel_sigma_mps, fix.vel_acc_mps), ACC_CAP * f.gnss_vel_sigma_mps)

    def position(self, fix: GnssFix, en: tuple[float, float], x: np.ndarray) -> Aid:
        """en: the fix in the local frame (LocalFrame.to_en)."""
        e, n = en
        # R: the measurement noise covariance
        return Aid(np.array([e, n]), x[:2].copy(), H_POS, np.eye(2) * self.sigma_pos(fix) ** 2)

    def velocity(self, fix: GnssFix, x: np.ndarray) -> Aid:
        hx, H = gnss_velocity_model(x)
        # R = (sigma_v^2 + (sigma_L |a|)^2) I: a latency known to within sigma_L (gnss_latency_sigma_s, off by
        # default) puts a fix's velocity up to that long behind the state's while the vehicle accelerates by |a|
        lag = self.f.gnss_latency_sigma_s * math.hypot(x[AX], x[AY])
        return Aid(np.array([fix.vel_e_mps, fix.vel_n_mps]), hx, H, np.eye(2) * (self.sigma_vel(fix) ** 2 + lag * lag))


class FreezeWatch:
    """A receiver's noise never repeats a fix to the last digit while the vehicle moves: a repeat
    at speed is a frozen (replayed or stuck) GNSS."""

    def __init__(self, freeze_speed_mps: float):
        self.freeze_speed_mps = freeze_speed_mps
        self.last: tuple | None = None          # (lat, lon, v_n, v_e) of the previous fix

    def check(self, fix: GnssFix, speed_mps: float, gnss_index: int) -> Alarm | None:
        """The freeze's alarm, if this fix repeats the last one while the vehicle moves."""
        key = (fix.lat_deg, fix.lon_deg, fix.vel_n_mps, fix.vel_e_mps)
        repeated, self.last = key == self.last, key
        if not repeated or speed_mps < self.freeze_speed_mps:
            return None
        return Alarm(fix.t_us, gnss_index, Sensor.GNSS_POS, "frozen", speed_mps, self.freeze_speed_mps, 0.0, "freeze")
