"""A blow at the IMU (a hard landing, a vehicle tipping over, a kerb struck): its readings set aside.

An IMU logged or streamed at 10 to 400 Hz is a point sample of its specific force, not the integral
of it. A blow lasts milliseconds and peaks at several g: the sample that happens to fall in it reads
5 g for the whole interval, 20 ms at 50 Hz, a velocity change of 1 m/s that never happened, and the
one beside it reads nothing of it at all. The autopilot's attitude is tumbling at the same moment,
so the levelled accelerometers, the yaw rate and the compass's heading are all off with it. On the
public real flights replayed by `tools/real_logs.py`, the landings and crashes whose IMU read more
than 3 g raised 16 alarms on accelerometer, gyro, compass and GNSS velocity within the 3 s after.

So a sample whose specific force exceeds IMPACT_G sets the IMU aside until HOLD_S after the last such
sample: nothing is fused or tested, the GNSS holds the estimate, and the velocity's uncertainty grows
by what the blow may have done, ((|f| - g) T)^2 per sample (`NavEKF.blow`). A flying or driving
vehicle's specific force stays well under it: a multicopter's thrust is about twice its weight, a
car corners and brakes at under 1 g.

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
IMPACT_G = 3.0          # |specific force| beyond this many g is a blow, not a manoeuvre
HOLD_S = 0.5            # s: the IMU is set aside this long after the last such sample
WINDOW_S = 10.0         # s ...
BUDGET_S = 2.0          # ... of which at most this much is set aside: more is not a blow


class Impact:
    """Decides, sample by sample, whether the IMU is set aside for a blow."""

    def __init__(self):
        self.until: int | None = None           # the IMU is set aside until this time (us)
        self._aside: deque[tuple[int, float]] = deque()     # (t_us, s set aside) within the last WINDOW_S
        self._aside_s = 0.0
        self._last_t: int | None = None
        self.said = self.overrun = self.overrun_said = False     # overrun: the budget was spent at least once
        self.peak_g = 0.0

    def check(self, s: ImuSample) -> tuple[bool, float]:
        """(set aside, the velocity variance the blow adds, (m/s)^2) for one IMU sample."""
        dt = 0.0 if self._last_t is None else min(max(s.t_us - self._last_t, 0) / 1e6, MAX_STEP_S)
        self._last_t = s.t_us
        f = math.sqrt(s.acc_x_mps2 ** 2 + s.acc_y_mps2 ** 2 + s.acc_z_mps2 ** 2)
        blow = f > IMPACT_G * G
        self._forget(s.t_us)
        if self._aside_s + dt > BUDGET_S:           # the window's budget is spent: tested as it reads
            self.overrun, self.until = True, None
            return False, 0.0
        if blow:
            self.until = s.t_us + int(HOLD_S * 1e6)
            self.peak_g = max(self.peak_g, f / G)
        if self.until is None or s.t_us > self.until:
            return False, 0.0
        self._aside.append((s.t_us, dt))
        self._aside_s += dt
        return True, ((f - G) * dt) ** 2 if blow else 0.0

    def _forget(self, t_us: int) -> None:
        """Drop what was set aside more than WINDOW_S ago (a time that jumped back: all of it)."""
        while self._aside and not 0 <= t_us - self._aside[0][0] <= WINDOW_S * 1e6:
            self._aside_s -= self._aside.popleft()[1]
        if not self._aside:
            self._aside_s = 0.0
