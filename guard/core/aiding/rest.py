"""The accelerometers at rest: an IMU that does not read gravity as gravity.

A vehicle at rest feels gravity and nothing else: its accelerometers' specific force is g long (9.78
to 9.83 m/s^2 over the earth; 9.80665 is taken), whatever its tilt. A calibrated MEMS accelerometer
reads that within a per cent or two: the README's public flights judged at rest read 9.54 to 9.97
m/s^2, all but the Erle boards of 2014 (10.11 to 10.38, 3 to 6 % high), one telemetry log (10.23) and
one Erle copter (`22-12-2014/37`) that read 8.26, 16 % low. An error on the axis gravity lies along
leaks into the levelled horizontal axes as the vehicle tilts (1.5 m/s^2 x sin 20 deg = 0.5 m/s^2 in a
copter's cruise): a bias guard's accel and gnss_vel tests read as an attack, and which the filter's
biases cannot learn, since it turns with the vehicle's tilt.

The check: in windows of WINDOW_S, where the vehicle is at rest, the length of the mean specific force
against g. At rest means: its gyro under STILL_RADPS on every axis, each accelerometer axis's spread
under QUIET_MPS2, the means of the window's two halves within STEADY_MPS2 of each other beyond what
their noise makes, and the GNSS, where a fix with a velocity came within FIX_FRESH_S, under STILL_MPS.
Off by more than TOL_MPS2 (0.75 m/s^2, the difference ArduPilot's pre-arm check allows between two of
its accelerometers, ARMING_ACCTHRESH) on SUSTAIN windows in a row, a WARNING says by how much, once per
episode (again only after a window back within it). At rest one orientation is seen: a scale error
and an offset look alike, and an offset across gravity changes the length by its square over 2g (1
m/s^2: 0.05). Nor can it tell a miscalibration from data injected into the IMU at rest, and it says
so. Any IMU rate: a window needs MIN_SAMPLES (a 1 Hz telemetry stream's five).

It is not an alarm and changes no test: it says what the accel and gnss_vel alarms of such an IMU in
flight may be.
"""

from __future__ import annotations

import math
import statistics
from collections import deque

from guard.model.events import Notice
from guard.model.samples import ImuSample

G = 9.80665
WINDOW_S = 5.0          # s per window
MIN_SAMPLES = 5         # IMU samples a window needs
STILL_RADPS = 0.05      # rad/s on every gyro axis: not turning (3 deg/s)
QUIET_MPS2 = 0.5        # m/s^2, each accelerometer axis's spread over the window: no manoeuvre, at most an
                        # idling motor's vibration
STEADY_MPS2 = 0.1       # m/s^2 between the means of the window's halves, beyond 3 sigma of their noise: the
                        # reading is not moving
STILL_MPS = 0.3         # m/s, the GNSS's horizontal speed at rest
FIX_FRESH_S = 2.0       # s: a fix older than this says nothing of now
TOL_MPS2 = 0.75         # m/s^2 off g: past ArduPilot's pre-arm tolerance between two accelerometers
SUSTAIN = 2             # windows in a row (10 s)
KEPT = 2000             # the latest windows' readings kept for the report's median (a week of a daemon
                        # at rest judges some 100,000)


class RestCheck:
    def __init__(self):
        self.past = 0                           # windows in a row past TOL_MPS2
        self.said = False                       # an episode is under way (said)
        self._fix: tuple[int, float] | None = None   # (t_us, horizontal speed) of the latest fix with a velocity
        self.readings: deque[float] = deque(maxlen=KEPT)  # |mean f| of the latest windows at rest
        self.judged = 0                         # windows at rest judged in all
        self.extremes: tuple[float, float] | None = None  # the least and greatest |mean f| of them
        self.gap()

    def gap(self) -> None:
        """A gap, a reboot, a blow set aside: the window under way is not continuous with what comes."""
        self._start: int | None = None
        self._last: int | None = None
        # the window's first and second half: each [count, sum f_x, sum f_y, sum f_z]; over both, the
        # sums of their squares
        self._first, self._second = [0, 0.0, 0.0, 0.0], [0, 0.0, 0.0, 0.0]
        self._sq = [0.0, 0.0, 0.0]
        self._still = True                      # the gyro, and the GNSS, said still throughout

    def fix(self, t_us: int, speed_mps: float | None) -> None:
        """One 3D fix's horizontal speed (None: the receiver sent no velocity)."""
        if speed_mps is not None:
            self._fix = (t_us, speed_mps)

    def imu(self, s: ImuSample) -> list[Notice]:
        """One IMU sample (its body axes: at rest the length of its specific force is all that counts)."""
        t = s.t_us
        if self._last is not None and (t <= self._last or t - self._last > WINDOW_S * 1e6 / MIN_SAMPLES * 2):
            self.gap()                          # back in time, or a silence: start again
            self.past = 0
        out: list[Notice] = []
        if self._start is not None and t >= self._start + WINDOW_S * 1e6:
            out = self._check(t)
            self.gap()
        if self._start is None:
            self._start = t
        self._last = t
        if max(abs(s.gyro_x_radps), abs(s.gyro_y_radps), abs(s.gyro_z_radps)) > STILL_RADPS:
            self._still = False
        fix = self._fix
        if fix is not None and 0 <= t - fix[0] <= FIX_FRESH_S * 1e6 and fix[1] >= STILL_MPS:
            self._still = False
        h = self._second if t >= self._start + WINDOW_S * 5e5 else self._first
        f = (s.acc_x_mps2, s.acc_y_mps2, s.acc_z_mps2)
        h[0] += 1
        for i in range(3):
            h[i + 1] += f[i]
            self._sq[i] += f[i] * f[i]
        return out

    def _check(self, t_us: int) -> list[Notice]:
        (n1, *s1), (n2, *s2) = self._first, self._second
        n = n1 + n2
        if not self._still or n < MIN_SAMPLES or n1 == 0 or n2 == 0:
            return self._not_at_rest()
        # per axis: mean m = (S1 + S2) / n, spread sd = sqrt(SQ / n - m^2); the halves' means S1/n1 and
        # S2/n2 differ by their noise alone up to 3 sd sqrt(1/n1 + 1/n2): past that, by STEADY_MPS2 more
        mean = [(a + b) / n for a, b in zip(s1, s2)]
        sd = [math.sqrt(max(self._sq[i] / n - mean[i] ** 2, 0.0)) for i in range(3)]
        steady = all(abs(a / n1 - b / n2) <= STEADY_MPS2 + 3.0 * d * math.sqrt(1 / n1 + 1 / n2)
                     for a, b, d in zip(s1, s2, sd))
        if max(sd) > QUIET_MPS2 or not steady:
            return self._not_at_rest()
        force = math.sqrt(sum(m * m for m in mean))
        self.readings.append(force)
        self.judged += 1
        low, high = self.extremes or (force, force)
        self.extremes = (min(low, force), max(high, force))
        if abs(force - G) <= TOL_MPS2:
            self.past, self.said = 0, False
            return []
        self.past += 1
        if self.past < SUSTAIN or self.said:
            return []
        self.said = True
        off = force - G
        leak = abs(off) * math.sin(math.radians(20.0))
        return [Notice(t_us, "warning", f"the accelerometers read {force:.2f} m/s^2 at rest over "
                       f"{SUSTAIN * WINDOW_S:g} s where g is {G:.2f}: {off:+.2f} ({100 * off / G:+.0f} %), past "
                       f"the {TOL_MPS2:g} m/s^2 ArduPilot's pre-arm check allows between two accelerometers: "
                       "miscalibrated (a scale or an offset) or data injected. Tilted 20 deg in flight, that is "
                       f"{leak:.1f} m/s^2 in the horizontal, an accel and gnss_vel bias to guard's tests: "
                       "calibrate the accelerometers")]

    def summary(self) -> dict | None:
        """What the windows at rest read (m/s^2): their number, the median of the latest KEPT (how
        many: `median_of`), least and greatest; None where the vehicle was never judged at rest."""
        if not self.judged:
            return None
        return {"windows": self.judged, "median_mps2": round(statistics.median(self.readings), 3),
                "median_of": len(self.readings), "min_mps2": round(self.extremes[0], 3),
                "max_mps2": round(self.extremes[1], 3)}

    def _not_at_rest(self) -> list[Notice]:
        self.past = 0
        return []
