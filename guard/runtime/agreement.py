"""How far a vehicle's levelled accelerometers and its GNSS velocity disagree, outside any filter: what
an accelerometer attack of a given size has to stand out from on this vehicle.

Over each window of W seconds between two GNSS fixes, the horizontal specific force guard integrates
(each IMU sample levelled with the autopilot's roll and pitch, guard.core.aiding.imu.level, turned to
east and north by guard's latest heading estimate, carried to each sample by the IMU's yaw rate) is
summed and compared with the change of the
receiver's velocity over the same window:

    e(W) = ( sum of a_EN dt  -  (v(t + W) - v(t)) ) / W          (m/s^2)

turned into the vehicle's own axes at the window's middle (a constant bias of the accelerometers is then
constant) and its horizontal length taken. With an exact attitude and a perfect IMU e is the
receiver's velocity noise over W (0.05 m/s over 1 s: 0.05 m/s^2) and falls as W grows. What stays is
an error the accelerometers carry for that long: their bias, which guard's filter learns, and the
autopilot's tilt error times g (1 degree: 0.17 m/s^2). How much e moves from one window to the next
is its Allan deviation at W (the square root of half the mean squared change between adjacent
windows; IEEE Std 952's measure of an inertial sensor's error against its averaging time): a constant
bias has a large e and a small Allan deviation. The filter follows its accelerometers' bias as a
random walk of `q_accel_bias_air_mps2` (0.01 m/s^2/sqrt(s): an Allan deviation of 0.016 at 8 s, as
ArduPilot's SITL reads); on real flights it reads 0.006 to 2 m/s^2, and a 0.5 m/s^2 bias written into
the flights that wander over WANDER_SAY_MPS2 was caught no more often than they alarmed without it
(README, "How far real flights' levelled accelerometers wander").

A window with |e| over OUTLIER_MPS2 (a receiver's jump, a blow at the IMU) is left out and counted; so
is one across a gap (no fix for 1.5 W, or fewer than MIN_IMU_HZ IMU samples a second). The heading is
the filter's: a heading a few degrees off turns the vehicle's own acceleration by as much (0.05 rad of
1.5 m/s^2: 0.08 m/s^2), so on a hard-flown vehicle part of e is guard's heading, not the IMU.
"""

from __future__ import annotations

import math
from array import array

import numpy as np

from guard.core.aiding.imu import level
from guard.core.aiding.tilt import Tilt
from guard.core.ekf import TH
from guard.model.events import Estimate
from guard.model.samples import Attitude, GnssFix, ImuSample

G = 9.80665
WINDOWS_S = (0.4, 1.0, 2.0, 4.0, 8.0)
SAY_WINDOW_S = 8.0      # the window guard replay's line is of
WANDER_SAY_MPS2 = 0.2   # an Allan deviation at 8 s over this: an accelerometer bias of a few tenths is within
                        # what the vehicle does (the real flights' attacks, README)
OUTLIER_MPS2 = 5.0      # a window this far off is a receiver's jump or a blow, not the IMU's error
MIN_IMU_HZ = 5.0        # a window with fewer IMU samples per second than this is not integrated
MAX_STEP_S = 0.25       # an IMU step longer than this is a gap: not integrated across (a 10 Hz IMU steps 0.1 s)


class Agreement:
    """A replay's listener: the levelled specific force integrated since the start (east, north), the
    IMU samples integrated and the heading, kept every TRACK_S; and each fix's velocity. The heading is
    the filter's latest estimate carried to each IMU sample by its yaw rate."""

    needs_tests = False
    TRACK_S = 0.02      # s between the integral's kept values (an hour's log: 180,000 of them)

    def __init__(self):
        self.tilt = Tilt()
        self.heading: float | None = None          # ENU yaw (rad) at the last IMU sample
        self._sum = [0.0, 0.0]
        self._n = 0
        self._t: float | None = None               # the last IMU sample's time (s)
        self._kept: float = -math.inf
        self.track = array("d")                    # t, sum E, sum N, n, yaw; flattened
        self.fixes = array("d")                    # t, v E, v N; flattened

    def on_sample(self, s) -> None:
        if isinstance(s, Attitude):
            self.tilt.set(s)
        elif isinstance(s, ImuSample):
            fwd, left, rate = level(s, *self.tilt.at(s))[:3]
            t = s.t_us / 1e6
            dt = 0.0 if self._t is None else t - self._t
            self._t = t
            if self.heading is None or not 0.0 < dt <= MAX_STEP_S:
                return
            self.heading += rate * dt
            c, sn = math.cos(self.heading), math.sin(self.heading)
            self._sum[0] += (c * fwd - sn * left) * dt
            self._sum[1] += (sn * fwd + c * left) * dt
            self._n += 1
            if t - self._kept >= self.TRACK_S:
                self._kept = t
                self.track.extend((t, self._sum[0], self._sum[1], self._n, self.heading))
        elif isinstance(s, GnssFix) and s.fix_ok and s.vel_n_mps is not None and s.vel_e_mps is not None:
            self.fixes.extend((s.t_us / 1e6, s.vel_e_mps, s.vel_n_mps))

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Estimate):
                self.heading = self._unwrapped(float(e.x[TH]))

    def _unwrapped(self, yaw: float) -> float:
        """yaw, by whole turns nearest the heading carried so far (so that the track interpolates)."""
        return yaw if self.heading is None else self.heading + math.remainder(yaw - self.heading, math.tau)

    def close(self) -> None:
        pass

    def rows(self) -> np.ndarray:
        """One row per fix within the track: t, sum E, sum N, n, v E, v N, yaw (the track at the fix's time)."""
        track = np.frombuffer(self.track, dtype=float).reshape(-1, 5)
        fixes = np.frombuffer(self.fixes, dtype=float).reshape(-1, 3)
        if len(track) < 2 or len(fixes) < 2:
            return np.zeros((0, 7))
        fixes = fixes[(fixes[:, 0] >= track[0, 0]) & (fixes[:, 0] <= track[-1, 0])]
        fixes = fixes[np.concatenate([[True], np.diff(fixes[:, 0]) > 0])]     # time order, once each
        at = [np.interp(fixes[:, 0], track[:, 0], track[:, i]) for i in range(1, 5)]
        return np.column_stack([fixes[:, 0], at[0], at[1], at[2], fixes[:, 1], fixes[:, 2], at[3]])

    def measure(self, windows: tuple[float, ...] = WINDOWS_S) -> list[dict] | None:
        """Per window length: windows measured and left out, the rms of e's length, e as a tilt, its
        Allan deviation and the rms of the GNSS acceleration's length; None where no window could be
        measured at any length (no IMU integrated beside the fixes)."""
        rows = self.rows()
        if len(rows) < 2:
            return None
        out = []
        for w in windows:
            e, acc, left_out, adjacent = discrepancies(rows, w)
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


def discrepancies(rows: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """(e, the GNSS acceleration, windows left out, adjacent), one row per window of about window_s
    between fixes (Agreement.rows()): e (m/s^2) in the body's axes (forward, left) at the window's middle fix,
    the GNSS acceleration (east, north); adjacent[i] whether window i begins where window i - 1 ended."""
    t = rows[:, 0]
    out, acc, adjacent, left_out, k, last_end = [], [], [], 0, 0, -1
    while k < len(t):
        j = int(np.searchsorted(t, t[k] + window_s - 1e-3))
        if j >= len(t):
            break
        span = t[j] - t[k]
        if span <= 0.0 or span > 1.5 * window_s or rows[j, 3] - rows[k, 3] < MIN_IMU_HZ * span:
            left_out += 1
            k = j
            continue
        dv = rows[j, 4:6] - rows[k, 4:6]
        e = (rows[j, 1:3] - rows[k, 1:3] - dv) / span
        if np.max(np.abs(e)) > OUTLIER_MPS2:
            left_out += 1
        else:
            yaw = rows[(k + j) // 2, 6]
            out.append(np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]]) @ e)
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
                 "vehicle does, and its test cannot tell one apart (README)")
    return line
