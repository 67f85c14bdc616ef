"""A blow at the IMU (a hard landing, a vehicle tipping over, a kerb struck): its readings set aside.

An IMU logged or streamed at 10 to 400 Hz is a point sample of its specific force, not the integral
of it. A blow lasts milliseconds and peaks at several g: the sample that happens to fall in it reads
5 g for the whole interval, 20 ms at 50 Hz, a velocity change of 1 m/s that never happened, and the
one beside it reads nothing of it at all. The autopilot's attitude is tumbling at the same moment,
so the levelled accelerometers, the yaw rate and the compass's heading are all off with it. On the
public real flights replayed by `tools/real_logs.py`, the landings and crashes whose IMU read more
than 3 g raised 16 alarms on accelerometer, gyro, compass and GNSS velocity within the 3 s after.

So a specific force beyond IMPACT_G, as a mean over MEAN_S (15 ms: a vibration faster than about
60 Hz averages out, and on a real 220 Hz PX4 quad with a badly damped IMU, 1,128 single samples of
13,511 passed 3 g in a minute, their 15 ms means 61; an IMU logged at 50 Hz or slower is its own
mean), sets the IMU aside until HOLD_S after the last such mean: nothing is fused or tested, the
GNSS holds the estimate, and the velocity's uncertainty grows by what the blow may have done,
((|f| - g) T)^2 per sample, T its interval and, at a blow's first mean, the samples it rose through
(`NavEKF.blow`). A flying or driving vehicle's specific force stays well under it: a multicopter's
thrust is about twice its weight, a car corners and brakes at under 1 g.

An IMU attack cannot hide behind it for long: blows are brief, and no more than BUDGET_S of any
WINDOW_S seconds is set aside; beyond that the IMU is used and tested as it comes (a WARNING says so
the first time). What it costs: an attack on the IMU in the HOLD_S after a real blow is tested only
from then on, and one written as a string of blows is tested WINDOW_S - BUDGET_S of every WINDOW_S.
"""

from __future__ import annotations

import math
from collections import deque

from guard.core.ekf import MAX_STEP_S
from guard.model.samples import ImuSample

G = 9.80665
IMPACT_G = 3.0          # |specific force| beyond this many g is a blow, not a manoeuvre ...
MEAN_S = 0.015          # s: ... as a mean over this long (under a 50 Hz IMU's interval)
HOLD_S = 0.5            # s: the IMU is set aside this long after the last such mean
WINDOW_S = 10.0         # s ...
BUDGET_S = 2.0          # ... of which at most this much is set aside: more is not a blow


class Impact:
    """Decides, sample by sample, whether the IMU is set aside for a blow."""

    def __init__(self):
        self.until: int | None = None           # the IMU is set aside until this time (us)
        self._aside: deque[tuple[int, float]] = deque()     # (t_us, s set aside) within the last WINDOW_S
        self._aside_s = 0.0
        self._last_t: int | None = None
        self._recent: deque[tuple[int, float, float, float]] = deque()    # the samples within MEAN_S
        self._covered = False                   # the stream has spanned MEAN_S
        self.said = self.overrun = self.overrun_said = False     # overrun: the budget was spent at least once
        self.peak_g = 0.0

    def check(self, s: ImuSample) -> tuple[bool, float]:
        """(set aside, the velocity variance the blow adds, (m/s)^2) for one IMU sample."""
        dt = 0.0 if self._last_t is None else min(max(s.t_us - self._last_t, 0) / 1e6, MAX_STEP_S)
        self._last_t = s.t_us
        f = self._mean_force(s)
        blow = f > IMPACT_G * G
        self._forget(s.t_us)
        if self._aside_s + dt > BUDGET_S:           # the window's budget is spent: tested as it reads
            self.overrun, self.until = True, None
            return False, 0.0
        span = 0.0
        if blow:
            if self.until is None or s.t_us > self.until:   # a new blow: the samples its mean rose through
                span = (s.t_us - self._recent[0][0]) / 1e6   # went by unset aside; their share is added too
            self.until = s.t_us + int(HOLD_S * 1e6)
            self.peak_g = max(self.peak_g, f / G)
        if self.until is None or s.t_us > self.until:
            return False, 0.0
        self._aside.append((s.t_us, dt))
        self._aside_s += dt
        return True, ((f - G) * (dt + span)) ** 2 if blow else 0.0

    def _mean_force(self, s: ImuSample) -> float:
        """|mean specific force| over the samples within MEAN_S up to this one (m/s^2); 0 until the
        stream has covered MEAN_S (a fast IMU's first sample alone is no mean)."""
        recent = self._recent
        if recent and not 0 <= s.t_us - recent[-1][0]:
            recent.clear()                          # time ran back (a reboot): start again
            self._covered = False
        recent.append((s.t_us, s.acc_x_mps2, s.acc_y_mps2, s.acc_z_mps2))
        while s.t_us - recent[0][0] >= MEAN_S * 1e6:
            recent.popleft()
            self._covered = True
        if not self._covered:
            return 0.0
        n = len(recent)
        # the sums taken in the samples' order, as sum() takes them
        sx = sy = sz = 0.0
        for _, fx, fy, fz in recent:
            sx += fx
            sy += fy
            sz += fz
        return math.sqrt((sx / n) ** 2 + (sy / n) ** 2 + (sz / n) ** 2)

    def _forget(self, t_us: int) -> None:
        """Drop what was set aside more than WINDOW_S ago (a time that jumped back: all of it)."""
        while self._aside and not 0 <= t_us - self._aside[0][0] <= WINDOW_S * 1e6:
            self._aside_s -= self._aside.popleft()[1]
        if not self._aside:
            self._aside_s = 0.0
