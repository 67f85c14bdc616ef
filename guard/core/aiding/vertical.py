"""The accelerometers' vertical reading against the GNSS altitude: an IMU that does not read the vehicle.

guard's filter is horizontal: the accelerometers' vertical axis enters no test. Yet it is the axis
a failing accelerometer shows first. Under vibration past its range an accelerometer clips, and the
mean of what it reads is no longer the mean of what it felt (vibration rectification): a real Erle
copter of the README hovered with its levelled vertical specific force at 0 to 3 m/s^2 for seconds
where gravity alone gives 9.8, and its horizontal axes were off by metres per second squared with it. A bias written into the vertical axis (false data injected into the IMU) shows the same way.

The check compares two measures of the vehicle's vertical acceleration over seconds: the IMU's
levelled specific force less gravity (f_up = -f_z - g, each sample levelled with the autopilot's roll
and pitch, guard.core.aiding.tilt), and the second difference of the GNSS altitude. Both are kept in
bins of BIN_S; at each bin's end, with the latest six bins' mean altitudes H,

    a_gnss = (h3 - 2 h2 + h1) / W^2,   h1, h2, h3 the means of bins (1, 2), (3, 4), (5, 6), W = 2 BIN_S

and a_imu the mean of f_up over bins 2 to 5 (the span whose acceleration the second difference
weighs). Their difference d is the receiver's altitude noise and the vehicle's own (0.01 to 1.6 m/s^2
at the median of each public flight of the README it is not said on, 2.9 at most on a hard-flown one
that holds its climb: README, "An IMU that does not read the vehicle") plus what the IMU gets wrong. Where |d| passes DIFF_MPS2 on SUSTAIN checks in a row while the GNSS shows the vehicle holding
its climb (|a_gnss| under STEADY_MPS2: a receiver's altitude jump is not the IMU's fault), something
does not read the vehicle, and a WARNING says what, with the figures, once per episode (again only
after QUIET_S of checks back under it):
- the accelerometers, where the mean of their own readings over the same span (in the body's axes,
  levelled by nothing) is not about g long: a clipped accelerometer's is not (2.8 m/s^2 on that
  copter);
- the attitude that levels them, where it is (within ATTITUDE_TOL_MPS2): the accelerometers read the
  vehicle and the roll and pitch the autopilot logged do not (a 2014 Erle copter of the README logs a
  roll that runs through 180 degrees and a pitch down to -78 while it hovers, its IMU reading 9.4
  m/s^2 in all). guard's horizontal tests, levelled with that attitude, are then off too.
It is not an alarm: the horizontal tests already alarm where the fault reaches them, and this says
what such alarms are likely to be.

It runs only on an IMU fast enough to integrate (a telemetry IMU at 1 to 4 Hz samples vibration, not
its mean), with the GNSS altitude of a 3D fix, and skips a bin that an IMU gap or a blow set aside
(guard.core.aiding.impact) left short.
"""

from __future__ import annotations

import math
from collections import deque

from guard.model.events import Notice
from guard.model.samples import ImuSample

G = 9.80665
BIN_S = 1.0             # s per bin
DIFF_MPS2 = 3.0         # m/s^2 between the IMU's vertical acceleration and the GNSS's: not noise
STEADY_MPS2 = 2.0       # the GNSS's own vertical acceleration under this: the vehicle holds its climb
SUSTAIN = 3             # checks in a row past DIFF_MPS2 (3 s)
QUIET_S = 30.0          # s of checks back under it before another episode is said
MIN_IMU = 5             # IMU samples a bin needs (a 10 Hz IMU: half of them)
MIN_FIXES = 1           # fixes a bin needs
ATTITUDE_TOL_MPS2 = 2.0  # |mean specific force| this close to g (the vehicle holds its climb to STEADY_MPS2):
                         # the accelerometers read the vehicle, and the attitude that levels them is wrong
LATE_FIX_US = 1_000_000  # a fix this far behind the bin under way is the latency's (guard.core.timebase)


def upward(s: ImuSample, phi: float, p: float) -> float:
    """The vehicle's upward acceleration as the IMU reads it: -f_z - g, f_z the specific force levelled
    with roll phi and pitch p (the z row of R_y(p) R_x(phi), guard.core.aiding.imu.level)."""
    cr, sr, cp, sp = math.cos(phi), math.sin(phi), math.cos(p), math.sin(p)
    return -(-sp * s.acc_x_mps2 + cp * sr * s.acc_y_mps2 + cp * cr * s.acc_z_mps2) - G


class VerticalCheck:
    def __init__(self):
        # the latest complete bins: (altitude, f_up, f_x, f_y, f_z), each its mean over the bin; None where short
        self.bins: deque = deque(maxlen=6)
        self._start: int | None = None          # the current bin's start (us)
        self._alt = [0.0, 0]                    # sum and count in the current bin
        self._up = [0.0, 0, 0.0, 0.0, 0.0]     # sum of f_up, count, sums of the body's specific force x, y, z
        self.past = 0                           # checks in a row past DIFF_MPS2
        self.said = False                       # an episode is under way (said)
        self._quiet_since: int | None = None

    def imu(self, s: ImuSample, phi: float, p: float) -> list[Notice]:
        """One IMU sample, with the roll and pitch that level it."""
        out = self._roll(s.t_us)
        u = self._up
        u[0] += upward(s, phi, p)
        u[1] += 1
        u[2] += s.acc_x_mps2
        u[3] += s.acc_y_mps2
        u[4] += s.acc_z_mps2
        return out

    def fix(self, t_us: int, alt_m: float) -> list[Notice]:
        """One 3D fix's altitude (m). A fix is stamped at its time of validity, up to a second behind the
        IMU's latest sample: one that late is counted in the bin under way."""
        late = self._start is not None and 0 < self._start - t_us <= LATE_FIX_US
        out = [] if late else self._roll(t_us)
        self._alt[0] += alt_m
        self._alt[1] += 1
        return out

    def gap(self) -> None:
        """A gap, a reboot, a blow set aside: what was kept is not continuous with what comes."""
        self.bins.clear()
        self._start = None
        self._alt, self._up = [0.0, 0], [0.0, 0, 0.0, 0.0, 0.0]
        self.past = 0

    def _roll(self, t_us: int) -> list[Notice]:
        if self._start is None or t_us < self._start:
            self.gap()
            self._start = t_us
            return []
        out: list[Notice] = []
        while t_us >= self._start + BIN_S * 1e6:
            ok = self._alt[1] >= MIN_FIXES and self._up[1] >= MIN_IMU
            n = self._up[1]
            self.bins.append((self._alt[0] / self._alt[1], self._up[0] / n, self._up[2] / n, self._up[3] / n,
                              self._up[4] / n) if ok else None)
            self._alt, self._up = [0.0, 0], [0.0, 0, 0.0, 0.0, 0.0]
            self._start += int(BIN_S * 1e6)
            out += self._check(self._start)
            if len(self.bins) == self.bins.maxlen and all(b is None for b in self.bins):
                self._start = t_us                  # a long silence: no use stepping through it
        return out

    def _check(self, t_us: int) -> list[Notice]:
        b = self.bins
        if len(b) < b.maxlen or any(x is None for x in b):
            self.past = 0
            return []
        w = 2 * BIN_S
        h1, h2, h3 = (b[0][0] + b[1][0]) / 2, (b[2][0] + b[3][0]) / 2, (b[4][0] + b[5][0]) / 2
        a_gnss = (h3 - 2 * h2 + h1) / (w * w)
        mid = list(b)[1:5]
        a_imu = sum(x[1] for x in mid) / 4
        force = math.sqrt(sum((sum(x[i] for x in mid) / 4) ** 2 for i in (2, 3, 4)))   # |mean f_body|
        if abs(a_imu - a_gnss) > DIFF_MPS2 and abs(a_gnss) < STEADY_MPS2:
            self.past += 1
            self._quiet_since = None
        else:
            self.past = 0
            if self._quiet_since is None:
                self._quiet_since = t_us
            elif self.said and t_us - self._quiet_since >= QUIET_S * 1e6:
                self.said = False
            return []
        if self.past < SUSTAIN or self.said:
            return []
        self.said = True
        if abs(force - G) < ATTITUDE_TOL_MPS2:
            return [Notice(t_us, "warning", f"the IMU levelled with the autopilot's roll and pitch reads the vehicle "
                           f"accelerating {a_imu:+.1f} m/s^2 upward over 4 s where its GNSS altitude says "
                           f"{a_gnss:+.1f}, though its accelerometers read {force:.1f} m/s^2 in all, as a vehicle "
                           "holding its climb does: the attitude is wrong (the autopilot's estimate, or its log), "
                           "and what guard levels with it is off too")]
        return [Notice(t_us, "warning", f"the accelerometers read the vehicle accelerating {a_imu:+.1f} m/s^2 "
                       f"upward over 4 s where its GNSS altitude says {a_gnss:+.1f}, and {force:.1f} m/s^2 in all "
                       f"where about {G:.1f} is due: they do not read the vehicle (clipping under vibration, "
                       "or data injected into them); their horizontal axes are likely off too, and accel and "
                       "gnss_vel alarms now may be this fault")]
