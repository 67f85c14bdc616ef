"""GNSS aiding: position (east, north) and velocity (east, north) of one receiver, and the freeze check.

    position  z = (e, n) of the fix in the local frame,  h(x) = (x, y),  H = H_POS
    velocity  z = (v_e, v_n),  h(x) = R(theta) (v_x, v_y),  H its Jacobian (gnss_velocity_model)
R is diagonal (but for the latency's part below, when set, and a held course's), from the receiver's own
accuracy figures where it sends them (as EKF2 does), bounded below by the configured floors and above by
ACC_CAP times them (a receiver, or a spoofer, that claims a huge error would otherwise blind every
test), or by what this receiver usually reports where it is poorer than that all along
(guard.core.aiding.receiver):
    position  sigma = max(gnss_pos_sigma_m, gnss_pos_acc_fraction * h_acc): h_acc counts the slow,
              correlated error too, which the filter follows (q_pos_m); the innovation sees the
              epoch-to-epoch part, about 0.4 of it on u-blox receivers
    velocity  sigma = max(gnss_vel_sigma_mps, vel_acc): the speed accuracy is an epoch's noise
and where it sends none, gnss_vel_unreported_mps and, for the position, gnss_pos_unreported_m per
unit of the fix's HDOP where it gives one (an older receiver reports its geometry, not its accuracy:
at HDOP 1, 0.5 m; the Erle PXF's receivers flew at HDOP 1.3 to 2, their position wandering against
their own velocity by a metre), else gnss_pos_unreported_m (real receivers' levels, as EKF3's
defaults, not the simulator's).
A receiver holds its course over ground where the vehicle moves too slowly for a course to mean
anything, and reports its speed along the last course it had (HELD_COURSE_MAX_MPS): a fix whose course
repeats the last one's to the last digit, that slowly but faster than its noise (HELD_NOISE), has its
velocity's direction taken as unknown: its speed, which the receiver did measure, is tested and fused
along the filter's own track, each channel against the variance along it, and across it nothing is
(held_speed); where the filter's own track is not
sure (its speed too near the noise, its direction too uncertain), the fix's vector is taken with R
widened by (2 |v|)^2 on both axes (a held course is off by up to the angle turned since, as far as twice
the speed), and so is the velocity a re-anchoring on that fix takes.
The velocity's R can also hold the receiver's latency, as far as it is unknown (latency_spread, off
by default): on the 47 real flights of the README the GNSS velocity innovations grow with the
acceleration, more along it than across it, as a fix 0.05 to 0.35 s late would make them on the
copters that ran inertially.
"""

from __future__ import annotations

import math

import numpy as np

from guard.core.aiding import Aid
from guard.core.aiding.receiver import LEVEL_WINDOW_S, ReceiverLevel, believed, bound
from guard.core.ekf import N_STATES, TH, VX, VY, X, Y, FilterConfig
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
# A receiver holds its course over ground while the vehicle moves too slowly for the course to mean anything
# (receivers' own low-speed rule): the real logs of the README held it below 0.3 to 2 m/s (copters' and
# planes' receivers, in tlogs and DataFlash) and a car's often up to 3, where the held course parted from
# the track by 0.55 to 1.9 m/s (median), against 0.2 to 0.4 for a fresh one. A course repeated to the last
# digit below this speed is taken as held. Above it a repeat is tested as it reads: at speed a receiver's
# noise moves its course every fix, and widening there would let a spoofer who repeats his course blind
# the velocity's test.
HELD_COURSE_MAX_MPS = 3.0
# Below this many times its velocity's noise a reported speed is mostly the receiver's noise, and so is
# its course, held or fresh: a vector of that length, whichever way it points, is what R already allows
# for. Above it a held course can stand across a turn. (Widened down to standing still, the real logs'
# hovering copters caught fewer 0.3 m/s position ramps, which their velocity gave away: README.)
HELD_NOISE = 2.0
# A held fix's speed is measured along the filter's own track (GnssAiding.held_speed) only where that track
# is sure: the filter's speed over this many times the velocity's noise (a reported speed just over the held
# rule's floor is biased up by it: +0.9 sigma at 2 sigma, +0.1 at 5) ...
HELD_SPEED_NOISE = 4.0
# ... and its direction known to within this (P's velocity across the track over the speed; 14 degrees)
HELD_TRACK_RAD = 0.25
# A course repeated "to the last digit": the course comes as an angle (GPS_RAW_INT's cdeg, DataFlash's
# degrees) and the speed apart, and the velocity built from them gives the same angle back to a few 1e-16
# rad, or 1e-9 where a source carries it as float32 components (a ULog's or DroneCAN's, of a receiver that
# sends speed and course); a fresh course's noise, a degree or so, comes this near the last one's about
# once in 10^4 fixes.
SAME_COURSE_RAD = 1e-6


class GnssAiding:
    """Builds the GNSS measurements, R from each fix's accuracy figures (see the module's docstring)."""

    def __init__(self, f: FilterConfig):
        self.f = f
        self._last_course: tuple | None = None     # the last fix's (course over ground rad from north, lat, lon)
        self.level = ReceiverLevel()                # what the receiver usually says of itself: the monitor feeds it

    def cap_pos(self) -> float:
        """The largest position noise a fix's own figures are taken at, m (receiver.bound)."""
        f, h = self.f, self.level.h_acc
        return bound(f.gnss_pos_sigma_m, ACC_CAP * f.gnss_pos_sigma_m,
                     None if h is None else f.gnss_pos_acc_fraction * h,
                     f.gnss_pos_acc_fraction * f.gnss_h_acc_usual_max_m)

    def cap_vel(self) -> float:
        """The largest velocity noise a fix's own figure is taken at, m/s (receiver.bound)."""
        f = self.f
        return bound(f.gnss_vel_sigma_mps, ACC_CAP * f.gnss_vel_sigma_mps, self.level.vel_acc,
                     f.gnss_vel_acc_usual_max_mps)

    def beyond_usual(self) -> str | None:
        """What to say of a receiver whose usual figures have passed the most its tuned vehicle's are
        believed to be (`gnss_h_acc_usual_max_m`, `gnss_vel_acc_usual_max_mps`, from guard tune): its
        figures are taken up to LEVEL_FACTOR times that most, no further (None: nothing to say). The
        monitor says it once."""
        f, level, parts = self.f, self.level, []
        h_settled, v_settled = level.settled()     # a receiver settling after power-on is not compared yet
        if f.gnss_vel_acc_usual_max_mps > 0.0 and v_settled and level.vel_acc > f.gnss_vel_acc_usual_max_mps \
                and f.use_gnss_velocity:
            parts.append(f"its velocity good to {level.vel_acc:.2f} m/s (gnss_vel_acc_usual_max_mps "
                         f"{f.gnss_vel_acc_usual_max_mps:g})")
        if f.gnss_h_acc_usual_max_m > 0.0 and h_settled and level.h_acc > f.gnss_h_acc_usual_max_m:
            parts.append(f"its position good to {level.h_acc:.1f} m (gnss_h_acc_usual_max_m "
                         f"{f.gnss_h_acc_usual_max_m:g})")
        if not parts:
            return None
        return (f"the receiver usually reports {' and '.join(parts)}, more than guard tune believes of this "
                "vehicle (twice the worst of its clean logs): its figures are taken only that far, so it may "
                "alarm; a receiver whose claims creep up may be one being readied for a spoof, or one that has "
                "fewer satellites than it ever had in its clean logs")

    def poor_as_usual(self) -> str | None:
        """What to say of a receiver whose usual figures take it past the fixed bound (ACC_CAP times the
        floors): its tests are that much blunter (None: nothing to say). The monitor says it once."""
        f, parts = self.f, []
        if self.cap_vel() > ACC_CAP * f.gnss_vel_sigma_mps and f.use_gnss_velocity:
            parts.append(f"its velocity good to {believed(self.level.vel_acc, f.gnss_vel_acc_usual_max_mps):.2f} m/s")
        if self.cap_pos() > ACC_CAP * f.gnss_pos_sigma_m:
            parts.append(f"its position good to {believed(self.level.h_acc, f.gnss_h_acc_usual_max_m):.1f} m")
        if not parts:
            return None
        return (f"the receiver usually reports {' and '.join(parts)} (its median over up to "
                f"{LEVEL_WINDOW_S:g} s of calm fixes): guard takes its word, so its GNSS tests are that much "
                "blunter, and an attack on it must be that much larger to be seen (a receiver that claims "
                "this all of a sudden is not believed)")

    def beyond_cap(self, fix: GnssFix) -> str | None:
        """What to say of a fix whose receiver calls itself worse than guard takes a receiver's word
        for (cap_pos, cap_vel; its HDOP, for one that reports no accuracy): its tests then assume the
        cap, and a receiver that poor may alarm where one that knows it is would not (None: nothing to
        say). The monitor says it once per filter."""
        f, parts = self.f, []
        cap_pos = self.cap_pos()
        if fix.h_acc_m and f.gnss_pos_acc_fraction * fix.h_acc_m > cap_pos:
            parts.append(f"its position good to {fix.h_acc_m:.1f} m only (guard takes up to "
                         f"{cap_pos / f.gnss_pos_acc_fraction:.3g} m)")
        elif not fix.h_acc_m and fix.hdop and f.gnss_pos_unreported_m * fix.hdop > ACC_CAP * f.gnss_pos_sigma_m:
            parts.append(f"an HDOP of {fix.hdop:.1f} (guard takes up to "
                         f"{ACC_CAP * f.gnss_pos_sigma_m / f.gnss_pos_unreported_m:g})")
        if f.use_gnss_velocity and fix.vel_acc_mps and fix.vel_acc_mps > self.cap_vel():
            parts.append(f"its velocity good to {fix.vel_acc_mps:.2f} m/s only (guard takes up to "
                         f"{self.cap_vel():.3g} m/s)")
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
        return min(max(f.gnss_pos_sigma_m, f.gnss_pos_acc_fraction * fix.h_acc_m), self.cap_pos())

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
        noise does), and likewise for one that reports its accuracy, per gnss_pos_unreported_m of the
        fix's noise (what one unit of HDOP is taken for): h_acc counts the slow error too, and a
        receiver that calls itself good to 8 m wanders by metres in seconds (a real PX4 copter's, with 7
        to 11 satellites: 23 m in 18 s, its velocity saying 8). Up to h_acc 1.25 m, q_pos_m as it was."""
        f = self.f
        if fix.h_acc_m:
            return f.q_pos_m * max(self.sigma_pos(fix) / f.gnss_pos_unreported_m, 1.0)
        if not fix.hdop:
            return f.q_pos_m
        return f.q_pos_m * min(max(fix.hdop, 1.0), ACC_CAP)

    def sigma_vel(self, fix: GnssFix, held: bool = False) -> float:
        """The velocity's noise on each axis; held (held_course): widened by twice the speed, as far as a
        held course can be off (turned back on itself)."""
        f = self.f
        if not fix.vel_acc_mps:
            sigma = f.gnss_vel_unreported_mps
        else:
            sigma = min(max(f.gnss_vel_sigma_mps, fix.vel_acc_mps), self.cap_vel())
        return math.hypot(sigma, 2.0 * math.hypot(fix.vel_e_mps, fix.vel_n_mps)) if held else sigma

    def position(self, fix: GnssFix, en: tuple[float, float], x: np.ndarray) -> Aid:
        """en: the fix in the local frame (LocalFrame.to_en)."""
        e, n = en
        # R: the measurement noise covariance
        return Aid(np.array([e, n]), x[:2].copy(), H_POS, np.eye(2) * self.sigma_pos(fix) ** 2)

    def forget_course(self) -> None:
        """A new filter: its first fix starts the course over (held_course compares with none)."""
        self._last_course = None

    def held_course(self, fix: GnssFix) -> bool:
        """Whether this fix's course over ground repeats the last fix's to the last digit while it moves
        slower than HELD_COURSE_MAX_MPS but faster than HELD_NOISE times its velocity's noise: a course
        the receiver held, not measured, and that may matter. Asked once per fix with a velocity, in
        order. A fix whose position repeats too is a frozen one, FreezeWatch's, not a held course."""
        speed = math.hypot(fix.vel_e_mps, fix.vel_n_mps)
        course = math.atan2(fix.vel_e_mps, fix.vel_n_mps) if speed > 0.0 else None
        last, self._last_course = self._last_course, (course, fix.lat_deg, fix.lon_deg)
        return (course is not None and last is not None and last[0] is not None
                and abs(course - last[0]) < SAME_COURSE_RAD
                and last[1:] != (fix.lat_deg, fix.lon_deg)
                and HELD_NOISE * self.sigma_vel(fix) < speed < HELD_COURSE_MAX_MPS)

    def velocity(self, fix: GnssFix, x: np.ndarray, accel_en: np.ndarray | None, ground: bool,
                 held: bool = False, P: np.ndarray | None = None) -> Aid:
        """accel_en: the vehicle's mean horizontal acceleration (east, north) since the last fix
        (guard.core.monitor), what a late fix's velocity lags by (latency_spread). held: its course was
        held by the receiver (held_course), its direction unknown: its speed is measured along the
        filter's own track where P says that track is sure (held_speed)."""
        hx, H = gnss_velocity_model(x)
        lag = self.latency_spread(accel_en, ground)
        if held:
            along = self.held_speed(fix, hx, H, P)
            if along is not None:
                z, H, R, u = along
                return Aid(z, hx, H, R + np.outer(lag, lag), axis=u)
        R = np.eye(2) * self.sigma_vel(fix, held) ** 2 + np.outer(lag, lag)
        return Aid(np.array([fix.vel_e_mps, fix.vel_n_mps]), hx, H, R)

    def held_speed(self, fix: GnssFix, hx: np.ndarray, H: np.ndarray, P: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """A held fix's speed |v|, the one thing in it measured, as a measurement of the filter's own
        speed |h(x)|: put in the east-north frame along the filter's track u = h(x) / |h(x)|, so that
        z - h(x) = (|v| - |h(x)|) u and H becomes u u^T H (the speed's Jacobian, along u). Across the
        track nothing is measured (z - h(x) is 0 there, H too) and R keeps the held fix's widened
        variance; along it, the receiver's own. The held course's error, the same fix after fix, is
        then no longer in the innovation. Returned with z, H and R: u, the axis the speed is tested
        along (Aid.axis): the detector tests east and north apart, and each channel's diagonal of S
        would hold the across-track widening wherever the track is off the axes (on a diagonal track a
        speed off by 4 sigma read 0.2 sigma on either); against S along u, each channel reads the
        speed's innovation times the track's share on its axis.
        None (the widened vector as it reads) unless the filter's own track is sure: its speed over
        HELD_SPEED_NOISE times the velocity's noise (a speed that near the noise is biased up by the
        held rule's own floor, and its direction is the noise's) and its direction known to within
        HELD_TRACK_RAD (P's velocity across the track over the speed: after a re-anchoring, or on GNSS
        alone through a turn, the filter's track may be as stale as the held course)."""
        sigma = self.sigma_vel(fix)
        speed = float(np.hypot(*hx))
        if P is None or speed <= HELD_SPEED_NOISE * sigma:
            return None
        u = hx / speed
        w = np.array([-u[1], u[0]])
        hw = w @ H
        if math.sqrt(max(float(hw @ P @ hw), 0.0)) > HELD_TRACK_RAD * speed:
            return None
        along = np.outer(u, u)
        z = math.hypot(fix.vel_e_mps, fix.vel_n_mps) * u
        R = sigma ** 2 * along + self.sigma_vel(fix, held=True) ** 2 * np.outer(w, w)
        return z, along @ H, R, u

    def latency_sigma(self, ground: bool) -> float:
        """sigma_L, s: how far the receiver's latency is unknown on this vehicle (0: off)."""
        return self.f.gnss_latency_sigma_s if ground else self.f.gnss_latency_sigma_air_s

    def latency_spread(self, accel_en: np.ndarray | None, ground: bool) -> np.ndarray:
        """sigma_L a (east, north): how far a fix's velocity may lag the state's when its receiver's
        latency is known to within sigma_L only (gnss_latency_sigma_air_s, gnss_latency_sigma_s on
        wheels; both off by default) and the vehicle accelerated by a since the last fix. A lag L puts
        the fix's velocity at v - L a, along the acceleration: R gains sigma_L^2 a a^T, not diagonal
        (NavEKF.fuse takes it whole). The detector tests east and north apart, each on its own
        variance, so an acceleration between the two widens both. a is the mean since the last fix of
        the filter's own velocity before this fix, as the IMU carried it (the fix's noise is not in
        it; on GNSS alone the monitor passes None). None (the first fix, a gap): 0."""
        sigma = self.latency_sigma(ground)
        if sigma <= 0.0 or accel_en is None:
            return np.zeros(2)
        return sigma * np.asarray(accel_en, dtype=float)


def across_track(R: np.ndarray, fix: GnssFix) -> float:
    """The 1-sigma noise of a fix's velocity across its track (what turns its course), from its R:
    sqrt(u^T R u), u the unit vector across the velocity (the larger axis of R when standing still)."""
    speed = math.hypot(fix.vel_e_mps, fix.vel_n_mps)
    if speed <= 0.0:
        return math.sqrt(float(np.max(np.linalg.eigvalsh(R))))
    u = np.array([-fix.vel_n_mps, fix.vel_e_mps]) / speed
    return math.sqrt(float(u @ R @ u))


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
