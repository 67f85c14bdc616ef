"""Replay throughput: `guard replay` against a bare pymavlink read of the same tlog, in one run.

    python tools/bench_replay.py [--minutes 10] [--repeat 3] [--vehicle ground]

The tlog is simulated: RAW_IMU at 50 Hz and GPS_RAW_INT at 10 Hz only (scenario `clean`, no
heartbeat: guard takes it for a vehicle that may move sideways unless `--vehicle ground`, which
tests the wheels' constraint too). Each side is timed --repeat times, interleaved, and the best
time of each is kept (the machines are shared and noisy); the ratio of the two is the figure to
compare. Then one more replay
is instrumented to show where the time goes: parsing (frames to samples), prediction, update
(innovations and fusion) and the detector; the rest is the core's own bookkeeping and events.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil                    # noqa: E402

from guard.config import parse                   # noqa: E402
from guard.core import monitor as core, ekf                      # noqa: E402
from guard.sources.tlog import TlogReader, tlog_samples   # noqa: E402
from guard.runtime.replay import replay                  # noqa: E402
from guard_sim import scenario                         # noqa: E402
from guard_sim.run import run                          # noqa: E402


def make_tlog(path: str, minutes: float) -> None:
    sc = scenario.load("clean")
    sc = dataclasses.replace(sc, duration_s=minutes * 60,
                             rates=dataclasses.replace(sc.rates, imu_hz=50.0, gnss_hz=10.0, heartbeat_hz=0.0))
    run(sc, 1, tlog=path)


def bare_pymavlink(path: str) -> int:
    conn = mavutil.mavlink_connection(path)
    n = 0
    while conn.recv_match() is not None:
        n += 1
    conn.close()
    return n


def timed(fn, *args):
    t = time.perf_counter()
    result = fn(*args)
    return time.perf_counter() - t, result


class Clock:
    """Wraps a function and adds up the time spent in it."""

    def __init__(self):
        self.total = 0.0

    def wrap(self, fn):
        def inner(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.total += time.perf_counter() - t
        return inner


def breakdown(path: str, cfg) -> dict[str, float]:
    """Seconds in parsing, prediction, update and detector for one instrumented replay."""
    reader = TlogReader(path)
    parse_s, n = timed(lambda: sum(1 for _ in tlog_samples(reader)))
    reader.close()
    clocks = {name: Clock() for name in ("prediction", "update", "detector")}
    originals = (ekf.NavEKF.predict, ekf.NavEKF.innovation, ekf.NavEKF.fuse, core.Monitor._test)
    ekf.NavEKF.predict = clocks["prediction"].wrap(ekf.NavEKF.predict)
    ekf.NavEKF.innovation = clocks["update"].wrap(ekf.NavEKF.innovation)
    ekf.NavEKF.fuse = clocks["update"].wrap(ekf.NavEKF.fuse)
    core.Monitor._test = clocks["detector"].wrap(core.Monitor._test)
    try:
        total, _ = timed(replay, path, cfg)
    finally:
        ekf.NavEKF.predict, ekf.NavEKF.innovation, ekf.NavEKF.fuse, core.Monitor._test = originals
    parts = {"parsing": parse_s, **{k: c.total for k, c in clocks.items()}}
    parts["other (core bookkeeping, events)"] = max(0.0, total - sum(parts.values()))
    parts["total"] = total
    return parts


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--vehicle", choices=("auto", "ground", "air"), default="auto",
                   help="monitor.vehicle for the replay (the tlog has no heartbeat: auto is air)")
    args = p.parse_args(argv)
    cfg = parse({"monitor": {"vehicle": args.vehicle}}, "--vehicle")
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.tlog")
        make_tlog(path, args.minutes)
        best_bare = best_guard = float("inf")
        for _ in range(args.repeat):
            t, n = timed(bare_pymavlink, path)
            best_bare = min(best_bare, t)
            t, report = timed(replay, path, cfg)
            best_guard = min(best_guard, t)
        assert sum(report["messages"].values()) == n, "both sides must read the same messages"
        print(f"tlog: {args.minutes:g} simulated minutes, {n} messages (RAW_IMU 50 Hz, GPS_RAW_INT 10 Hz), "
              f"{os.path.getsize(path) / 1e6:.1f} MB")
        print(f"pymavlink read : {n / best_bare:10,.0f} messages/s  ({best_bare:.2f} s)")
        print(f"guard replay   : {n / best_guard:10,.0f} messages/s  ({best_guard:.2f} s)")
        print(f"ratio guard/pymavlink: {best_bare / best_guard:.2f}  (target >= 0.25)")
        parts = breakdown(path, cfg)
        total = parts.pop("total")
        print(f"where the time goes (one instrumented replay, {total:.2f} s):")
        for name, secs in parts.items():
            print(f"  {name:<34} {secs:6.2f} s  {100 * secs / total:5.1f} %  {1e6 * secs / n:6.1f} us/message")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
