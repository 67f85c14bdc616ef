"""`guard tune` on one process against several, in one run: the ratio of the two times, and whether
the profiles are the same (they must be, to the bit).

    python tools/bench_tune.py [LOG ...] [--jobs N] [--minutes 2] [--logs 2]

Without LOGs, --logs clean drives of --minutes each are simulated (scenario `clean`, seeds 1, 2, ...).
Each side is timed once (a tune is 10 or 11 replays of every log, long enough to time once); the
machines are shared and noisy, so the ratio is the figure to compare, not the times.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from guard.config import Config                           # noqa: E402
from guard.runtime.tune import default_jobs, tune         # noqa: E402
from guard_sim import scenario                            # noqa: E402
from guard_sim.run import run                             # noqa: E402


def timed(logs: list[str], jobs: int) -> tuple[float, dict]:
    t0 = time.perf_counter()
    profile, _ = tune(logs, Config(), say=lambda line: None, jobs=jobs)
    return time.perf_counter() - t0, profile


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="*", help="clean logs to tune on (default: simulated drives)")
    ap.add_argument("--jobs", type=int, default=default_jobs(),
                    help="processes for the second run (default: every core)")
    ap.add_argument("--minutes", type=float, default=2.0, help="length of each simulated drive")
    ap.add_argument("--logs", dest="n_logs", type=int, default=2, help="how many drives to simulate")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as work:
        logs = list(args.logs)
        if not logs:
            sc = scenario.load("clean")
            for seed in range(1, args.n_logs + 1):
                logs.append(str(Path(work) / f"clean{seed}.tlog"))
                run(dataclasses.replace(sc, duration_s=args.minutes * 60), seed, tlog=logs[-1])
        one, p1 = timed(logs, 1)
        many, pn = timed(logs, args.jobs)
    print(f"guard tune on {len(logs)} log(s)")
    print(f"  one process        : {one:.1f} s")
    print(f"  {args.jobs} processes        : {many:.1f} s")
    print(f"  ratio              : {one / many:.2f}x quicker on {args.jobs}; the profiles "
          f"{'the same' if p1 == pn else 'DIFFER'}")
    return 0 if p1 == pn else 1


if __name__ == "__main__":
    sys.exit(main())
