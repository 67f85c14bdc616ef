"""GNSS aiding: position (east, north) and velocity (east, north) of one receiver, and the freeze check.

    position  z = (e, n) of the fix in the local frame,  h(x) = (x, y),  H = H_POS
    velocity  z = (v_e, v_n),  h(x) = R(theta) (v_x, v_y),  H its Jacobian (gnss_velocity_model)
R is the configured noise, diagonal.
"""

from __future__ import annotations

import math

import numpy as np

from guard.core.aiding import Aid
from guard.core.ekf import N_STATES, TH, VX, VY, X, Y, FilterConfig
from guard.core.geo import LocalFrame
from guard.model.samples import GnssFix

H_POS = np.zeros((2, N_STATES)); H_POS[0, X] = H_POS[1, Y] = 1.0


def gnss_velocity_model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h(x) = (v_e, v_n) = R(theta) (v_x, v_y), and its Jacobian."""
    th, vx, vy = x[TH], x[VX], x[VY]
    cs, sn = math.cos(th), math.sin(th)
    H = np.zeros((2, N_STATES))
    H[0, TH], H[0, VX], H[0, VY] = -vx * sn - vy * cs, cs, -sn
    H[1, TH], H[1, VX], H[1, VY] = vx * cs - vy * sn, sn, cs
    return np.array([vx * cs - vy * sn, vx * sn + vy * cs]), H


class GnssAiding:
    """Builds the GNSS measurements; `R_pos`, `R_vel` from the filter's configuration."""

    def __init__(self, f: FilterConfig):
        # R: measurement noise covariance of each measurement set
        self.R_pos = np.eye(2) * f.gnss_pos_sigma_m ** 2
        self.R_vel = np.eye(2) * f.gnss_vel_sigma_mps ** 2

    def position(self, fix: GnssFix, frame: LocalFrame, x: np.ndarray) -> Aid:
        e, n = frame.to_en(fix.lat_deg, fix.lon_deg)
        return Aid(np.array([e, n]), x[:2].copy(), H_POS, self.R_pos)

    def velocity(self, fix: GnssFix, x: np.ndarray) -> Aid:
        hx, H = gnss_velocity_model(x)
        return Aid(np.array([fix.vel_e_mps, fix.vel_n_mps]), hx, H, self.R_vel)


class FreezeWatch:
    """A receiver's noise never repeats a fix to the last digit while the vehicle moves: a repeat
    at speed is a frozen (replayed or stuck) GNSS."""

    def __init__(self, freeze_speed_mps: float):
        self.freeze_speed_mps = freeze_speed_mps
        self.last: tuple | None = None          # (lat, lon, v_n, v_e) of the previous fix

    def frozen(self, fix: GnssFix, speed_mps: float) -> bool:
        key = (fix.lat_deg, fix.lon_deg, fix.vel_n_mps, fix.vel_e_mps)
        repeated, self.last = key == self.last, key
        return repeated and speed_mps >= self.freeze_speed_mps
