"""The filter's recent past: what a rewind needs to undo a GNSS attack, and what a late receiver needs.

- `epochs`: the filter before each GNSS epoch's fusion, over the last `rewind_s`;
- `imu_log`: every IMU fusion since the oldest epoch kept, each row with its sensor (a rewind re-runs
  them, GNSS and the sensors judged attacked left out);
- `states`: with a receiver latency, the state after each IMU fusion, back over the latency (a late
  fix is compared with the state of its own time).
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import numpy as np

from guard.core.ekf import TH, NavEKF
from guard.model.sensors import Sensor

REWIND_S = 20.0        # s of filter history kept to undo what an attack fed the filter before its alarm


class Epoch(NamedTuple):
    t_us: int
    x: np.ndarray
    P: np.ndarray


class ImuFusion(NamedTuple):
    t_us: int
    z: np.ndarray
    H: np.ndarray
    R: np.ndarray
    angle_rows: tuple[int, ...]
    sensors: tuple[Sensor | None, ...]      # the sensor of each row (None: a constraint, no sensor's)


class Blow(NamedTuple):
    """A blow the IMU could not measure (guard.core.aiding.impact): the velocity variance it added,
    which a rewind adds again."""

    t_us: int
    dv_var: float


class Manoeuvre(NamedTuple):
    """On GNSS alone, the acceleration's change the IMU saw (guard.core.aiding.manoeuvre), which a
    rewind adds again."""

    t_us: int
    da: float
    T: float


def keep_since(history: deque, t_us: float, at: int = 0) -> None:
    """Drop the entries of a history of tuples whose time (item `at`) is older than t_us."""
    while history and history[0][at] < t_us:
        history.popleft()


def state_minus(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b for two filter states, the heading's difference wrapped to (-pi, pi]."""
    d = a - b
    d[TH] = math.remainder(d[TH], math.tau)
    return d


class History:
    def __init__(self, rewind_s: float, delay_s: float, fuse_hz: float):
        self.rewind_s = rewind_s
        self.delay_s = delay_s
        self.epochs: deque[Epoch] = deque()
        self.imu_log: deque[ImuFusion | Blow | Manoeuvre] = deque()
        self.states: deque = deque(maxlen=int((delay_s + 1.0) * fuse_hz) + 2)   # [t_us, x] pairs

    def __len__(self) -> int:
        return len(self.epochs)

    def epoch(self, t_us: int, x: np.ndarray, P: np.ndarray) -> None:
        """The filter before a GNSS epoch's fusion, at the state's own time."""
        self.epochs.append(Epoch(t_us, x.copy(), P.copy()))
        keep_since(self.epochs, t_us - self.rewind_s * 1e6)

    def imu_fused(self, t_us: int, fusion: ImuFusion | None, x: np.ndarray) -> None:
        """After an IMU fusion at t_us (None: no row was fused): keep it while an epoch may need it."""
        if fusion is not None:
            self.imu_log.append(fusion)
        # a rewind re-runs the fusions after its epoch: those before the oldest one kept are not needed
        keep_since(self.imu_log, self.epochs[0].t_us if self.epochs else math.inf)
        if self.delay_s > 0:
            self.states.append((t_us, x.copy()))

    def blow(self, t_us: int, dv_var: float) -> None:
        """A blow's added velocity variance, kept while an epoch may need it."""
        if self.epochs:
            self.imu_log.append(Blow(t_us, dv_var))

    def manoeuvre(self, t_us: int, da: float, T: float) -> None:
        """The acceleration's change the IMU saw on GNSS alone, kept while an epoch may need it."""
        if self.epochs:
            self.imu_log.append(Manoeuvre(t_us, da, T))

    def oldest_x(self) -> np.ndarray | None:
        return self.epochs[0].x if self.epochs else None

    def delayed(self, t_us: int, now_us: int, x_now: np.ndarray) -> np.ndarray:
        """The filter's state delay_s before t_us, interpolated between the stored IMU-fusion states
        (the current state last). The innovation is formed against it and the correction applied to
        the current state with the current P (a delayed fix's usual approximation)."""
        then = t_us - self.delay_s * 1e6
        states = self.states
        while len(states) > 1 and states[1][0] <= then:
            states.popleft()
        pts = [*states, (now_us, x_now)]
        for (t0, x0), (t1, x1) in zip(pts, pts[1:]):
            if t0 <= then < t1:
                return x0 + state_minus(x1, x0) * ((then - t0) / (t1 - t0))
        return pts[0][1].copy()     # older than the history (the first fixes): the oldest state there is

    def shift(self, dx: np.ndarray) -> None:
        """A correction made now applies to the stored states too: the next late fix sees it."""
        for _, x in self.states:
            x += dx

    def anchored(self, fix_t_us: int, x_fix: np.ndarray) -> None:
        """The estimate was set to a fix (a re-anchoring): a rewind goes no further back than it, and a
        late fix is compared with the states from it on. The states before it are the estimate that
        could not be held: moved by the anchor's correction they would keep its runaway velocity, and
        the next late fix would meet it and alarm again at once. With a latency, the anchor itself is
        stored at the time the fix shows (x_fix: the state there), so that the fix and those after
        it are compared with where the anchor puts the vehicle at their own times."""
        self.epochs.clear()
        self.imu_log.clear()
        self.states.clear()
        if self.delay_s > 0:
            self.states.append((fix_t_us - int(self.delay_s * 1e6), x_fix.copy()))

    def rewind(self, ekf: NavEKF, epochs: int, now_us: int, leave_out: frozenset[Sensor] = frozenset()) -> int | None:
        """Undo the last `epochs` GNSS epochs: back to the filter before the attack's first sample was
        fused, then the IMU fusions since, GNSS left out, and predict to now. The rows of the sensors in
        `leave_out` (those judged attacked now) are left out too: a compass excluded by an alarm of its
        own fed the filter a turn over its test's run before that alarm, and fed again it turns the
        heading for the rest of the flight (a real copter whose compass was disturbed at take-off: its
        heading after the first GNSS rewind 24 degrees from the autopilot's on average, 6 with the
        compass's rows left out). Over the whole span, not only from the onset of the sensor's own
        alarm's run: a real compass is disturbed before its test's run begins (left out from the run's
        onset only, the 47 real flights of the README raised 170 alarms against 159, one copter's
        standing GNSS alarm going on 15 times more). What it costs: where an ambiguous alarm excluded
        the sensor that was not the attacked one (a gyro bias in the air, `mag|gyro`, the compass
        excluded), the good rows left out are the compass's. The bias states come back with the rest
        (not the oldest epoch's for every rewind: in the filter's first seconds those are start-up
        guesses, and coasting on them keeps a GNSS that agrees again out). Returns the time rewound to
        (None: no history), from which the estimate coasts."""
        epochs = min(epochs, len(self.epochs))     # a run longer than the history: as far back as it goes
        if epochs < 1:
            return None
        t0, x, P = self.epochs[-epochs]
        delayed, states = self.delay_s > 0, [(t0, x.copy())]   # with a receiver latency: re-run states
        ekf.x, ekf.P, t = x.copy(), P.copy(), t0
        for entry in self.imu_log:
            if entry.t_us <= t0:
                continue
            ekf.predict((entry.t_us - t) / 1e6)
            t = entry.t_us
            if isinstance(entry, Blow):
                ekf.blow(entry.dv_var)
                continue
            if isinstance(entry, Manoeuvre):
                ekf.manoeuvred(entry.da, entry.T)
                continue
            _, z, H, R, angle, sensors = entry
            if leave_out and any(s in leave_out for s in sensors):
                rows = [i for i, s in enumerate(sensors) if s not in leave_out]
                if not rows:
                    continue
                angle = tuple(rows.index(i) for i in angle if i in rows)
                z, H, R = z[rows], H[rows], R[np.ix_(rows, rows)]
            r, S, PHT = ekf.innovation(z, H @ ekf.x, H, R, angle_rows=angle)
            ekf.fuse(r, S, H, R, PHT)
            if delayed:
                states.append((t, ekf.x.copy()))
        ekf.predict((now_us - t) / 1e6)
        self.epochs.clear()
        self.imu_log.clear()
        if delayed:                 # the states before t0 stand; those after it are the re-run's
            kept = [st for st in self.states if st[0] < t0]
            self.states.clear()
            self.states.extend(kept + states)
        return t0
