"""The receiver's latency, from clean logs: replay them at several `filter.gnss_delay_s` and keep the
one that leaves the largest margin.

    python tools/gnss_delay.py LOG.tlog [LOG.tlog ...] [--config guard.toml] [--delays 0 0.05 0.1]

A fix shows the vehicle as it was some tens of milliseconds before its time stamp; in turns and speed
changes an unmodelled latency reads as a GNSS attack and eats the margin. For each delay the table
gives, per log, the largest CUSUM statistic/threshold of the run and its sensor (1.0 = an alarm),
and the number of alarms; the delay with the smallest worst ratio is suggested. Use logs without an
attack, with turns and speed changes (a straight line at constant speed shows no latency).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from guard.config import load                    # noqa: E402
from guard.errors import GuardError              # noqa: E402
from guard.runtime.replay import replay                  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("logs", nargs="+", help="clean tlogs (no attack), with turns and speed changes")
    p.add_argument("--config", help="guard's TOML config (its gnss_delay_s is replaced)")
    p.add_argument("--delays", nargs="+", type=float, default=[0.0, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.25])
    args = p.parse_args(argv)
    try:
        base = load(args.config)
    except GuardError as e:
        print(f"gnss_delay: {e}", file=sys.stderr)
        return 2
    for log in args.logs:
        if not Path(log).is_file():
            print(f"gnss_delay: {log}: no such file", file=sys.stderr)
            return 2
    print("gnss_delay_s | " + " | ".join(Path(log).name for log in args.logs) + " | worst")
    best = None
    for delay in args.delays:
        if not 0.0 <= delay <= 1.0:
            print(f"gnss_delay: --delays: {delay}: must be within 0 .. 1 s", file=sys.stderr)
            return 2
        flt = dataclasses.replace(base.monitor.filter, gnss_delay_s=delay)
        cfg = dataclasses.replace(base, monitor=dataclasses.replace(base.monitor, filter=flt))
        cells, worst = [], 0.0
        for log in args.logs:
            report = replay(log, cfg)
            sensor, ratio = max(report["peak_ratio"].items(), key=lambda kv: kv[1], default=("-", 0.0))
            cells.append(f"{ratio:.2f} ({sensor}), {len(report['alarms'])} alarms")
            worst = max(worst, ratio)
        print(f"{delay:.3f} | " + " | ".join(cells) + f" | {worst:.2f}", flush=True)
        if best is None or worst < best[1]:
            best = (delay, worst)
    print(f"suggested: gnss_delay_s = {best[0]:g} (largest statistic/threshold {best[1]:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
