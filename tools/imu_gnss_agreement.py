"""How far a vehicle's levelled accelerometers and its GNSS velocity disagree, outside any filter.

    python tools/imu_gnss_agreement.py FLIGHT.bin [FLIGHT.ulg FLIGHT.tlog ...] [--latency 0.2]
        [--windows 0.4 1 2 4 8] [--jobs 2] [--json out.json]

Over each window of W seconds between two GNSS fixes, the horizontal specific force guard integrates
(each IMU sample levelled with the autopilot's roll and pitch, as guard.core.aiding.imu.level does,
turned to east and north by guard's own heading estimate) is summed and compared with the change of
the receiver's velocity over the same window:

    e(W) = ( sum of a_EN dt  -  (v(t + W) - v(t)) ) / W          (m/s^2, east and north)

turned into the vehicle's own axes at the window's middle (a constant bias of the accelerometers is
then constant), and its horizontal length taken.
With an exact attitude and a perfect IMU e is the receiver's velocity noise over W (0.05 m/s over
1 s: 0.05 m/s^2) and falls as W grows. What stays as W grows is an error the accelerometers carry
for that long: their bias, and the autopilot's tilt error times g (1 degree: 0.17 m/s^2), which
guard's filter models as a slowly walking bias (filter.q_accel_bias_air_mps2). The table gives,
per W, the rms of e, e in degrees of tilt (atan(e / g)), and how much e moves from one window to
the next, its Allan deviation at W (the square root of half the mean squared change between
adjacent windows; IEEE Std 952's measure of an inertial sensor's error against its averaging time):
a constant bias, which guard's filter learns, has a large rms and a small Allan deviation; what the
filter cannot follow, and what its GNSS velocity test then sees, is the Allan deviation at the
scales of seconds. Beside them, the rms of the GNSS acceleration itself (how hard the vehicle
manoeuvred). A window with |e| over OUTLIER_MPS2 (a receiver's
jump, a blow at the IMU) is left out and counted; so is one across a gap (no fix for 1.5 W, or an IMU
under MIN_IMU_HZ).

The heading is the filter's (its estimate at each fix, interpolated between them): a heading a few
degrees off turns the vehicle's own acceleration by as much (0.05 rad of 1.5 m/s^2: 0.08 m/s^2), so
on a hard-flown vehicle part of e is guard's heading, not the IMU. `--latency` compares each fix
with the IMU that long before it (a receiver's latency, guard tune's filter.gnss_delay_s).

A log guard cannot read, or without windows to measure, is named with the reason and skipped.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from guard.core.aiding.imu import level        # noqa: E402
from guard.core.aiding.tilt import Tilt        # noqa: E402
from guard.core.ekf import TH                  # noqa: E402
from guard.errors import GuardError            # noqa: E402
from guard.model.events import Estimate        # noqa: E402
from guard.model.samples import Attitude, GnssFix, ImuSample   # noqa: E402
from guard.runtime.replay import replay        # noqa: E402

G = 9.80665
WINDOWS_S = (0.4, 1.0, 2.0, 4.0, 8.0)
OUTLIER_MPS2 = 5.0      # a window this far off is a receiver's jump or a blow, not the IMU's error
MIN_IMU_HZ = 5.0        # a window with fewer IMU samples per second than this is not integrated
MAX_STEP_S = 0.1        # an IMU step longer than this is a gap: not integrated across


class Recorder:
    """A replay's listener: the levelled specific force of each IMU sample, each fix's velocity and
    the filter's heading at each fix."""

    def __init__(self):
        self.tilt = Tilt()
        self.imu: list[tuple[float, float, float]] = []      # t (s), forward, left (m/s^2)
        self.fixes: list[tuple[float, float, float]] = []    # t (s), east, north (m/s)
        self.heading: list[tuple[float, float]] = []         # t (s), ENU yaw (rad)

    def on_sample(self, s) -> None:
        if isinstance(s, Attitude):
            self.tilt.set(s)
        elif isinstance(s, ImuSample):
            fwd, left = level(s, *self.tilt.at(s))[:2]
            self.imu.append((s.t_us / 1e6, fwd, left))
        elif isinstance(s, GnssFix) and s.fix_ok and s.vel_n_mps is not None and s.vel_e_mps is not None:
            self.fixes.append((s.t_us / 1e6, s.vel_e_mps, s.vel_n_mps))

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Estimate):
                self.heading.append((e.t_us / 1e6, float(e.x[TH])))

    def close(self) -> None:
        pass


def discrepancies(imu: np.ndarray, fixes: np.ndarray, heading: np.ndarray, window_s: float,
                  latency_s: float = 0.0) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """(e, the GNSS acceleration, windows left out, adjacent), one row per window of about window_s
    between fixes: e (m/s^2) in the body's axes (forward, left) at the window's middle, the GNSS
    acceleration (east, north); adjacent[i] whether window i begins where window i - 1 ended (none
    left out between them)."""
    t_i = imu[:, 0]
    t_f = fixes[:, 0] - latency_s
    th = np.interp(t_i, heading[:, 0], np.unwrap(heading[:, 1]))
    c, s = np.cos(th), np.sin(th)
    dt = np.diff(t_i, prepend=t_i[0])
    dt[(dt > MAX_STEP_S) | (dt < 0.0)] = 0.0
    # the specific force integrated from the first sample: a window's sum is a difference of two
    sum_e = np.cumsum((c * imu[:, 1] - s * imu[:, 2]) * dt)
    sum_n = np.cumsum((s * imu[:, 1] + c * imu[:, 2]) * dt)
    out, acc, adjacent, left_out, k, last_end = [], [], [], 0, 0, -1
    while k < len(t_f):
        j = int(np.searchsorted(t_f, t_f[k] + window_s - 1e-3))
        if j >= len(t_f):
            break
        span = t_f[j] - t_f[k]
        i0, i1 = np.searchsorted(t_i, [t_f[k], t_f[j]])
        if span <= 0.0 or span > 1.5 * window_s or i1 >= len(t_i) or i1 - i0 < MIN_IMU_HZ * span:
            left_out += 1
            k = j
            continue
        dv = fixes[j, 1:3] - fixes[k, 1:3]
        e = (np.array([sum_e[i1] - sum_e[i0], sum_n[i1] - sum_n[i0]]) - dv) / span
        if np.max(np.abs(e)) > OUTLIER_MPS2:
            left_out += 1
        else:
            # turned into the body's axes (forward, left) at the window's middle: a constant bias of the
            # accelerometers turns with the vehicle in east and north, not in its own axes
            mid = th[(i0 + i1) // 2]
            out.append(np.array([[math.cos(mid), math.sin(mid)], [-math.sin(mid), math.cos(mid)]]) @ e)
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


def measure(path: str, windows: tuple[float, ...] = WINDOWS_S, latency_s: float = 0.0) -> dict:
    """Per window length: windows measured and left out, the rms of e's length (the horizontal vector's),
    its Allan deviation, and the rms of the GNSS acceleration's length."""
    rec = Recorder()
    try:
        replay(path, listeners=[rec])
    except GuardError as e:
        return {"log": path, "skipped": str(e)}
    if len(rec.imu) < 2 or len(rec.fixes) < 2 or not rec.heading:
        return {"log": path, "skipped": "no IMU samples, fixes with a velocity, or heading estimate to compare"}
    imu, fixes, heading = np.array(rec.imu), np.array(rec.fixes), np.array(rec.heading)
    rows = []
    for w in windows:
        e, acc, left_out, adjacent = discrepancies(imu, fixes, heading, w, latency_s)
        if len(e) == 0:
            rows.append({"window_s": w, "windows": 0, "left_out": left_out})
            continue
        rms = float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
        adev = allan_deviation(e, adjacent)
        rows.append({"window_s": w, "windows": len(e), "left_out": left_out, "rms_mps2": round(rms, 3),
                     "tilt_deg": round(math.degrees(math.atan(rms / G)), 2),
                     "allan_mps2": None if adev is None else round(adev, 3),
                     "gnss_accel_rms_mps2": round(float(np.sqrt(np.mean(np.sum(acc ** 2, axis=1)))), 3)})
    if not any(r["windows"] for r in rows):
        return {"log": path, "skipped": f"no window with fixes on both ends and the IMU at {MIN_IMU_HZ:g} Hz or "
                                        "more (telemetry's IMU is too slow to integrate)"}
    return {"log": path, "latency_s": latency_s, "rows": rows}


def show(result: dict) -> str:
    if "skipped" in result:
        return f"{result['log']}: skipped, {result['skipped']}"
    lines = [f"{result['log']}: (latency {result['latency_s']:g} s)",
             "  window   windows  left out   rms e (m/s^2)  as tilt (deg)  Allan dev. (m/s^2)  GNSS accel rms (m/s^2)"]
    for r in result["rows"]:
        if not r["windows"]:
            lines.append(f"  {r['window_s']:5.1f} s  {0:8d}  {r['left_out']:8d}")
            continue
        adev = "-" if r["allan_mps2"] is None else f"{r['allan_mps2']:.3f}"
        lines.append(f"  {r['window_s']:5.1f} s  {r['windows']:8d}  {r['left_out']:8d}  {r['rms_mps2']:14.3f}"
                     f"  {r['tilt_deg']:13.2f}  {adev:>18s}  {r['gnss_accel_rms_mps2']:22.3f}")
    return "\n".join(lines)


def _one(job):
    return measure(*job)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", help="flight logs guard reads (tlog, DataFlash .bin, ULog)")
    ap.add_argument("--windows", type=float, nargs="+", default=list(WINDOWS_S), help="window lengths, s")
    ap.add_argument("--latency", type=float, default=0.0, help="the receiver's latency, s (default 0)")
    ap.add_argument("--jobs", type=int, default=1, help="logs measured at once")
    ap.add_argument("--json", help="write the figures here too")
    args = ap.parse_args(argv)
    if any(w <= 0.0 for w in args.windows) or args.latency < 0.0 or args.jobs < 1:
        ap.error("windows must be positive, the latency not negative and --jobs at least 1")
    missing = [p for p in args.logs if not Path(p).is_file()]
    if missing:
        print(f"error: {missing[0]}: no such file", file=sys.stderr)
        return 2
    jobs = [(p, tuple(args.windows), args.latency) for p in args.logs]
    if args.jobs > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(args.jobs) as ex:
            results = list(ex.map(_one, jobs))
    else:
        results = [_one(j) for j in jobs]
    for r in results:
        print(show(r))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
