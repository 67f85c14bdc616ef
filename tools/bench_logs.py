"""Log reading throughput: guard's DataFlash and ULog readers against the bare library read of the same file.

    python tools/bench_logs.py [--minutes 10] [--repeat 3] [--log FILE ...]

The simulator writes --minutes of the `clean` scenario (its own rates: IMU 50 Hz, GNSS 10 Hz,
heartbeat 1 Hz) as a DataFlash .bin and a ULog .ulg; each --log adds a real log. For every file,
three things are timed:
- the bare library read: for .bin, pymavlink's `mavlink_connection(path)` and `recv_match(type=...)`
  over the types guard reads (and, as a second figure, the plain all-types `recv_match()` loop); for
  .ulg, `pyulog.ULog(path, message_name_filter_list=...)` with the topics guard reads;
- guard's reader alone: `guard.sources.open_log(path)` and `.samples()` to the end;
- guard's whole replay: `guard.runtime.replay.replay(path)`, reader, core and report.
Each is timed --repeat times, interleaved, and the best time of each is kept. The libraries count
messages and guard counts samples (a .bin's GPS and GPA make one fix, its MAG rides on the IMU
sample), so the figures to compare are the ratios of times on the same file: bare time / guard time
(first bare line), 1 as fast as the library, 0.5 half as fast. They are measured in one run on a
shared machine: absolute rates depend on whatever else runs there, the ratios much less.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pymavlink import mavutil                    # noqa: E402
from pyulog import ULog                          # noqa: E402

from guard.sources import log_format, open_log   # noqa: E402
from guard.sources.ulog.load import TOPICS       # noqa: E402
from guard.runtime.replay import replay          # noqa: E402
from guard_sim import scenario                         # noqa: E402
from guard_sim.run import run                          # noqa: E402

# the DataFlash types guard decodes: samples (IMU, GPS, GPA, MAG, ATT), the vehicle (MSG, VER) and
# the autopilot's verdicts (MSG, ERR, the EKF innovation test ratios XKF4/NKF4/EKF4)
DF_TYPES = ["IMU", "GPS", "GPA", "MAG", "ATT", "MSG", "VER", "ERR", "XKF4", "NKF4", "EKF4"]


def make_logs(tmp: str, minutes: float) -> list[str]:
    sc = scenario.load("clean")
    paths = [os.path.join(tmp, "sim.bin"), os.path.join(tmp, "sim.ulg")]
    run(dataclasses.replace(sc, duration_s=minutes * 60), 1, bin=paths[0], ulg=paths[1])
    return paths


def bare_dataflash(path: str, types: list[str] | None) -> int:
    conn = mavutil.mavlink_connection(path)
    n = 0
    while conn.recv_match(type=types) is not None:
        n += 1
    conn.close()
    return n


def bare_ulog(path: str) -> int:
    with contextlib.redirect_stdout(io.StringIO()):        # pyulog prints what it finds wrong
        ulog = ULog(path, message_name_filter_list=TOPICS)
    return sum(len(d.data["timestamp"]) for d in ulog.data_list)


def guard_reader(path: str) -> int:
    with open_log(path) as source:
        return sum(1 for _ in source.samples())


def guard_replay(path: str) -> int:
    return sum(replay(path)["samples"].values())


def best_of(repeat: int, sides: dict) -> dict[str, tuple[float, int]]:
    """Best time and count of each side (name -> function of nothing), timed interleaved."""
    best = {name: (float("inf"), 0) for name in sides}
    for _ in range(repeat):
        for name, fn in sides.items():
            t = time.perf_counter()
            n = fn()
            best[name] = min(best[name], (time.perf_counter() - t, n))
    return best


def bench(path: str, label: str, repeat: int) -> None:
    if log_format(path) == "ulog":
        sides = {"pyulog ULog (guard's topics)": lambda: bare_ulog(path)}
    else:
        sides = {"pymavlink recv_match(type=guard's)": lambda: bare_dataflash(path, DF_TYPES),
                 "pymavlink recv_match() all types": lambda: bare_dataflash(path, None)}
    sides |= {"guard reader (open_log, samples)": lambda: guard_reader(path),
              "guard replay": lambda: guard_replay(path)}
    best = best_of(repeat, sides)
    bare_t = next(iter(best.values()))[0]
    (reader_t, samples), (replay_t, _) = best["guard reader (open_log, samples)"], best["guard replay"]
    print(f"{label}: {os.path.getsize(path) / 1e6:.1f} MB, {samples} samples")
    for name, (t, n) in best.items():
        unit = "messages" if name.startswith("py") else "samples"
        print(f"  {name:<36} {n / t:10,.0f} {unit}/s  ({n} in {t:.2f} s)")
    print(f"  ratio reader/bare: {bare_t / reader_t:.2f}   ratio replay/bare: {bare_t / replay_t:.2f}"
          "   (bare time / guard time)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=10.0, help="simulated minutes (default 10)")
    p.add_argument("--repeat", type=int, default=3, help="timings of each side, best kept (default 3)")
    p.add_argument("--log", action="append", default=[], metavar="FILE", help="a real .bin or .ulg (repeatable)")
    args = p.parse_args(argv)
    for path in args.log:
        if not os.path.isfile(path) or log_format(path) not in ("dataflash", "ulog"):
            p.error(f"--log {path}: not a DataFlash or ULog file")
    with tempfile.TemporaryDirectory() as tmp:
        for path in make_logs(tmp, args.minutes):
            bench(path, f"simulated {Path(path).suffix} ({args.minutes:g} min, clean)", args.repeat)
        for path in args.log:
            bench(path, Path(path).name, args.repeat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
