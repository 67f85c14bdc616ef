"""How far a vehicle's levelled accelerometers and its GNSS velocity disagree, outside any filter: what
an accelerometer attack of a given size has to stand out from on this vehicle.

Over each window of W seconds between two GNSS fixes, the horizontal specific force guard integrates
(each IMU sample levelled with the autopilot's roll and pitch, guard.core.aiding.imu.level, turned to
east and north by guard's latest heading estimate, carried to each sample by the IMU's yaw rate) is
summed and compared with the change of the receiver's velocity over the same window. Their
difference d (m/s) is what a constant error e of the accelerometers, in the vehicle's own axes
(forward, left), would give over the window:

    d = sum of a_EN dt - (v(t + W) - v(t)) = M e,   M = sum of R(theta) dt = [[C, -S], [S, C]]

(C, S the sums of cos theta dt and sin theta dt), so e = M^-1 d, exactly so through a turn; a window
that turned so far that M is near singular (|(C, S)| under MIN_ALIGNED of the window) is left out,
and its length taken. With an exact attitude and a perfect IMU e is the receiver's velocity noise
over W (0.05 m/s over 1 s: 0.05 m/s^2) and falls as W grows. What stays is an error the
accelerometers carry for that long: their bias, which guard's filter learns, and the autopilot's
tilt error times g (1 degree: 0.17 m/s^2). How much e moves from one window to the next is its Allan
deviation at W (the square root of half the mean squared change between adjacent windows, of the
vector here; IEEE Std 952's measure of an inertial sensor's error against its averaging time): a
constant bias has a large e and a small Allan deviation. The filter follows its accelerometers' bias
as a random walk of `q_accel_bias_air_mps2` (0.01 m/s^2/sqrt(s): an Allan deviation of the vector of
0.023 at 8 s, 0.016 per axis; ArduPilot's SITL flights read 0.018 to 0.021); the real flights of the
README read 0.004 to 2.2 m/s^2, and a 0.5 m/s^2 bias written into the half over their median (0.21)
was caught within 10 s in 13 of 57 runs, 8 of those windows alarming without it (README, "How far
real flights' levelled accelerometers wander").

A window with |e| over OUTLIER_MPS2 (a receiver's jump, a blow at the IMU) is left out and counted;
so is one across a gap (no fix for 1.5 W, or an IMU step over MAX_STEP_S, or a sample that is not a
number: not integrated). The IMU's time going back by more than BACK_S (an
autopilot's reboot) starts a new segment: no window spans two; less, the sample is out of order and
left out. The heading is the filter's: a heading a few degrees off turns the
vehicle's own acceleration by as much (0.05 rad of 1.5 m/s^2: 0.08 m/s^2), so on a hard-flown vehicle
part of e is guard's heading, not the IMU.

`LiveWander` is the same for `guard run`: every LIVE_CHECK_S of the samples' time it measures the 8 s
Allan deviation over what it holds (the latest LIVE_KEEP_S of the samples' time, the newest stretch
first and older ones between reboots for what is left of it, in at most LIVE_SEGMENTS stretches even
through a boot loop: a daemon's memory stays bounded), and once LIVE_MIN_PAIRS pairs of adjacent
windows show it over WANDER_SAY_MPS2 it says so, once, and lets go of what it held.
"""

from __future__ import annotations

import math
from array import array

import numpy as np

from guard.core.aiding.imu import level
from guard.core.aiding.tilt import Tilt
from guard.core.ekf import TH
from guard.model.events import Estimate
from guard.runtime.every import Live
from guard.model.samples import Attitude, GnssFix, ImuSample

G = 9.80665
WINDOWS_S = (0.4, 1.0, 2.0, 4.0, 8.0)
SAY_WINDOW_S = 8.0      # the window guard replay's line is of
WANDER_SAY_MPS2 = 0.2   # an Allan deviation at 8 s over this: an accelerometer bias of a few tenths is within
                        # what the vehicle does (the real flights' attacks, README)
OUTLIER_MPS2 = 5.0      # a window this far off is a receiver's jump or a blow, not the IMU's error
MAX_STEP_S = 0.25       # an IMU step longer than this is a gap: not integrated across (a 10 Hz IMU steps 0.1 s)
MIN_ALIGNED = 0.5       # |(C, S)| / W under this: the window turned too far for M to be solved
BACK_S = 1.0            # s an IMU sample's time may go back and be a sample out of order (left out); further
                        # back is a reboot, which starts a new segment. A fix more than this from the IMU's
                        # time is on another clock (the one before a reboot) and left out
TRACK = ("t", "sum_e", "sum_n", "gaps", "cos", "sin")     # a kept row of the integrals
LIVE_CHECK_S = 60.0     # guard run measures what it holds this often (the samples' time) ...
LIVE_KEEP_S = 600.0     # ... over the latest this much of it, across reboots (1.6 MB of integrals at 50 rows a
                        # second; up to 12 MB where every sample of a 400 Hz IMU is a gap, each kept) ...
LIVE_SEGMENTS = 3       # ... in at most this many stretches between reboots
LIVE_MIN_PAIRS = 10     # pairs of adjacent 8 s windows before it says anything (88 s of fixes and IMU at least)


class Agreement:
    """A replay's listener: the levelled specific force integrated since the start (east, north), the
    IMU's gaps counted and the sums of cos and sin of the heading, kept every TRACK_S and at each gap; and each fix's
    velocity. The heading is the filter's latest estimate carried to each IMU sample by its yaw rate."""

    needs_tests = False
    TRACK_S = 0.02      # s between the integrals' kept values (an hour's log: 180,000 of them)

    def __init__(self):
        self.tilt = Tilt()
        self.heading: float | None = None          # ENU yaw (rad) at the last IMU sample
        self.segments: list[tuple[array, array]] = []     # (track, fixes) of each stretch of forward time
        self._new_segment()

    def _new_segment(self) -> None:
        self._sums = [0.0] * 5                     # sum E, sum N, gaps, sum cos, sum sin
        self._t: float | None = None               # the last IMU sample's time (s)
        self._kept = -math.inf
        self.track, self.fixes = array("d"), array("d")    # TRACK rows; t, v E, v N: flattened
        self.segments.append((self.track, self.fixes))

    def on_sample(self, s) -> None:
        if isinstance(s, Attitude):
            self.tilt.set(s)
        elif isinstance(s, ImuSample):
            fwd, left, rate = level(s, *self.tilt.at(s))[:3]
            t = s.t_us / 1e6
            if self._t is not None and t < self._t:
                if t > self._t - BACK_S:                    # a sample out of order: not integrated
                    return
                self._new_segment()                         # time went back: a reboot
            dt = 0.0 if self._t is None else t - self._t
            self._t = t
            if self.heading is None or dt <= 0.0:
                return
            if dt > MAX_STEP_S or not (math.isfinite(fwd) and math.isfinite(left) and math.isfinite(rate)):
                self._sums[2] += 1                          # a gap: no window across it is measured
                self._keep(t)
                return
            self.heading += rate * dt
            c, sn = math.cos(self.heading), math.sin(self.heading)
            sums = self._sums
            sums[0] += (c * fwd - sn * left) * dt
            sums[1] += (sn * fwd + c * left) * dt
            sums[3] += c * dt
            sums[4] += sn * dt
            if t - self._kept >= self.TRACK_S:
                self._keep(t)
        elif isinstance(s, GnssFix) and s.fix_ok and s.vel_n_mps is not None and s.vel_e_mps is not None \
                and math.isfinite(s.vel_n_mps) and math.isfinite(s.vel_e_mps):
            t = s.t_us / 1e6
            if self._t is not None and abs(t - self._t) <= BACK_S:    # not one stamped on the clock before a
                self.fixes.extend((t, s.vel_e_mps, s.vel_n_mps))      # reboot, nor before the IMU speaks

    def _keep(self, t: float) -> None:
        self._kept = t
        self.track.extend((t, *self._sums))

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Estimate) and math.isfinite(yaw := float(e.x[TH])):
                # by whole turns nearest the heading carried so far, so that the track's sums run on
                self.heading = yaw if self.heading is None or not math.isfinite(self.heading) \
                    else self.heading + math.remainder(yaw - self.heading, math.tau)

    def close(self) -> None:
        pass

    def measure(self, windows: tuple[float, ...] = WINDOWS_S) -> list[dict] | None:
        """Per window length: windows measured and left out, the rms of e's length, e as a tilt, its
        Allan deviation and the rms of the GNSS acceleration's length; None where no window could be
        measured at any length (no IMU integrated beside the fixes)."""
        segments = self._rows()
        out = []
        for w in windows:
            e, acc, left_out, adjacent = windows_of(segments, w)
            if len(e) == 0:
                out.append({"window_s": w, "windows": 0, "left_out": left_out})
                continue
            rms = float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
            adev = allan_deviation(e, adjacent)
            out.append({"window_s": w, "windows": len(e), "left_out": left_out, "rms_mps2": round(rms, 3),
                        "tilt_deg": round(math.degrees(math.atan(rms / G)), 2),
                        "allan_mps2": None if adev is None else round(adev, 3),
                        "gnss_accel_rms_mps2": round(float(np.sqrt(np.mean(np.sum(acc ** 2, axis=1)))), 3)})
        return out if any(r["windows"] for r in out) else None

    def _rows(self) -> list[np.ndarray]:
        """rows() of each segment that has two or more."""
        return [r for track, fixes in self.segments if len(r := rows(track, fixes)) >= 2]


class LiveWander(Live, Agreement):
    """guard run's wander (a sink): `say(line)` once, where the 8 s Allan deviation over the latest
    LIVE_KEEP_S passes WANDER_SAY_MPS2 over at least LIVE_MIN_PAIRS pairs of adjacent windows (see the
    module's docstring). `checked`: the last measure, (Allan deviation or None, adjacent pairs), made at `checked_us`."""

    def __init__(self, say):
        super().__init__()
        self.live(say, LIVE_CHECK_S)
        self.checked: tuple[float | None, int] = (None, 0)
        self.checked_us: int | None = None

    def ticks(self, s) -> bool:
        return isinstance(s, ImuSample)

    def check(self, t_us: int) -> None:
        """Measure what it holds at t_us (after letting go of what is older than LIVE_KEEP_S); say the
        line where it shows the wander."""
        self._trim(t_us / 1e6)
        e, _, _, adjacent = windows_of(self._rows(), SAY_WINDOW_S)
        pairs = int(np.count_nonzero(adjacent[1:]))
        self.checked, self.checked_us = (allan_deviation(e, adjacent), pairs), t_us
        adev = self.checked[0]
        if adev is None or pairs < LIVE_MIN_PAIRS or adev <= WANDER_SAY_MPS2:
            return
        self.tell(t_us, f"accelerometers wander {adev:.2f} m/s^2 from the GNSS over {SAY_WINDOW_S:g} s: a bias of a "
                  "few tenths is within what this vehicle does, its test rarely tells one apart")

    def let_go(self) -> None:
        self.segments, self.track, self.fixes = [], array("d"), array("d")

    def _new_segment(self) -> None:
        super()._new_segment()
        del self.segments[:-LIVE_SEGMENTS]          # a boot loop, never reaching a check, holds no more

    def _trim(self, t: float) -> None:
        """Hold the latest LIVE_KEEP_S of the samples' time at t: the newest stretch back from t, then each
        older one back from its own end, for what is left."""
        left, kept = LIVE_KEEP_S, []
        for i, (track, fixes) in enumerate(reversed(self.segments)):
            times = np.frombuffer(track, dtype=float)[0::len(TRACK)]
            end = t if i == 0 else (float(times[-1]) if len(times) else -math.inf)
            if left <= 0.0 or not math.isfinite(end):
                continue
            n = int(np.searchsorted(times, end - left))
            del times
            del track[:n * len(TRACK)]
            n = int(np.searchsorted(np.frombuffer(fixes, dtype=float)[0::3], end - left))
            del fixes[:n * 3]
            if len(track):
                left -= end - track[0]
            kept.append((track, fixes))
        self.segments[:] = kept[::-1] if kept else self.segments[-1:]


def windows_of(segments: list[np.ndarray], window_s: float) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """discrepancies() over every segment's rows, joined: (e, the GNSS acceleration, windows left out,
    adjacent), no window across two segments."""
    parts = [discrepancies(r, window_s) for r in segments]
    if not parts:
        return np.zeros((0, 2)), np.zeros((0, 2)), 0, np.zeros(0, dtype=bool)
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), sum(p[2] for p in parts),
            np.concatenate([p[3] for p in parts]))


def rows(track: array, fixes: array) -> np.ndarray:
    """One row per fix within a segment's track: t, then the track's columns at the fix's time (TRACK
    after t), then the fix's v E, v N."""
    tr = np.frombuffer(track, dtype=float).reshape(-1, len(TRACK))
    fx = np.frombuffer(fixes, dtype=float).reshape(-1, 3)
    if len(tr) < 2 or len(fx) < 2:
        return np.zeros((0, len(TRACK) + 2))
    fx = fx[(fx[:, 0] >= tr[0, 0]) & (fx[:, 0] <= tr[-1, 0])]
    fx = fx[np.sort(np.unique(fx[:, 0], return_index=True)[1])] if len(fx) else fx   # once each,
    fx = fx[np.argsort(fx[:, 0], kind="stable")]                                         # in time order
    at = [np.interp(fx[:, 0], tr[:, 0], tr[:, i]) for i in range(1, len(TRACK))]
    return np.column_stack([fx[:, 0], *at, fx[:, 1], fx[:, 2]])


def discrepancies(r: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """(e, the GNSS acceleration, windows left out, adjacent), one row per window of about window_s
    between fixes (rows()): e (m/s^2) in the body's axes (forward, left), M^-1 d; the GNSS
    acceleration (east, north); adjacent[i] whether window i begins where window i - 1 ended."""
    t = r[:, 0]
    out, acc, adjacent, left_out, k, last_end = [], [], [], 0, 0, -1
    while k < len(t):
        j = max(int(np.searchsorted(t, t[k] + window_s - 1e-3)), k + 1)
        if j >= len(t):
            break
        span = t[j] - t[k]
        step = r[j] - r[k]          # the sums over the window: E, N, gaps, cos, sin (columns 1 to 5)
        c, s = step[4], step[5]
        aligned = math.hypot(c, s)
        if span <= 0.0 or span > 1.5 * window_s or step[3] != 0.0 or aligned < MIN_ALIGNED * span:
            left_out += 1
            k = j
            continue
        dv = step[6:8]
        d = step[1:3] - dv
        e = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]]) / (aligned * aligned)
        if not np.all(np.abs(e) <= OUTLIER_MPS2):           # NaN too
            left_out += 1
        else:
            out.append(e)
            acc.append(dv / span)
            adjacent.append(k == last_end)
            last_end = j
        k = j
    return np.array(out).reshape(-1, 2), np.array(acc).reshape(-1, 2), left_out, np.array(adjacent, dtype=bool)


def allan_deviation(e: np.ndarray, adjacent: np.ndarray) -> float | None:
    """sqrt(mean |e_i - e_(i-1)|^2 / 2) over adjacent windows (|.| the horizontal vector's length);
    None without two adjacent windows."""
    pairs = np.flatnonzero(adjacent[1:]) + 1
    if len(pairs) == 0:
        return None
    d = e[pairs] - e[pairs - 1]
    return float(np.sqrt(0.5 * np.mean(np.sum(d ** 2, axis=1))))


def said(rows: list[dict] | None) -> str | None:
    """guard replay's line: the wander at SAY_WINDOW_S, and what it means where it is large."""
    at = next((r for r in rows or () if r["window_s"] == SAY_WINDOW_S and r.get("allan_mps2") is not None), None)
    if at is None:
        return None
    line = (f"the levelled accelerometers against the GNSS velocity: they wander {at['allan_mps2']:.2f} m/s^2 over "
            f"{SAY_WINDOW_S:g} s (Allan deviation, {at['windows']} windows)")
    if at["allan_mps2"] > WANDER_SAY_MPS2:
        line += (f", over {WANDER_SAY_MPS2:g}: an accelerometer bias of a few tenths of a m/s^2 is within what this "
                 "vehicle does, and its test rarely tells one apart (README)")
    return line
