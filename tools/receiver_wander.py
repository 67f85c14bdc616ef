"""How far a receiver's positions wander against its own velocity, and what guard's model allows.

    python tools/receiver_wander.py FOLDER_OR_LOG [...] [--lags 1 2 5 10 20 40 80 160] [--jobs 2]
        [--config PROFILE.toml] [--json out.json]

For each log and lag T: the structure function D(T) of the receiver's position less its own
velocity's integral, per axis, against what guard's default model of its fixes allows
(guard.runtime.position_wander says how each figure is made; `guard replay` prints the 10 s one), and
its growth from 10 to 80 s (0.5 a random walk, 1 a drift, 0 a bounded error). The totals: at 10 and
80 s, how many logs wander past the model; which wander further at 10 s than the largest random walk
guard tune fits allows (a fault or a spoof); and the growth's median. A log guard cannot read is named
with the reason and skipped.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from guard.config import load                          # noqa: E402
from guard.errors import GuardError                    # noqa: E402
from guard.runtime.position_wander import (LAGS_S, LONG_S, SAY_LAG_S, SHORT_S, PositionWander,  # noqa: E402
                                           beyond_tune, ratio_at)
from guard.runtime.replay import replay                # noqa: E402
from tools.real_logs import logs_in                    # noqa: E402


def measure(job: tuple[str, tuple[float, ...], str | None]) -> dict:
    """{"log", **PositionWander.measure's} or {"log", "skipped": why}; the model of the config's filter."""
    path, lags, config = job
    try:
        cfg = load(config)
        wander = PositionWander(cfg.monitor.filter)
        replay(path, cfg, listeners=[wander])
    except GuardError as e:
        return {"log": path, "skipped": str(e)}
    got = wander.measure(lags)
    if got is None:
        return {"log": path, "skipped": f"{len(wander.sigma)} fixes with a velocity, too few"}
    return {"log": path, **got}


def show(r: dict) -> str:
    name = Path(r["log"]).name
    if "skipped" in r:
        return f"{name}: skipped, {r['skipped']}"
    figures = " ".join(f"{x['lag_s']:g}s {x['wander_m']:.2f}/{x['model_m']:.2f}" for x in r["lags"])
    grows = f"; grows as T^{r['exponent']:.2f}" if "exponent" in r else ""
    rate = f" at {r['rate_hz']:g} Hz" if r["rate_hz"] else ""
    return (f"{name}: {r['fixes']} fixes{rate}, median speed {r['speed_mps']:.2f} m/s; "
            f"wander/model (m): {figures}{grows}")


def summary(results: list[dict]) -> list[str]:
    done = [r for r in results if "skipped" not in r]
    lines = []
    for lag in (SHORT_S, LONG_S):
        ratios = [x for r in done if (x := ratio_at(r, lag)) is not None]
        if ratios:
            lines.append(f"at {lag:g} s: {len(ratios)} logs, wander over the model's {statistics.median(ratios):.2f} "
                         f"times at the median; past twice the model on {sum(1 for x in ratios if x > 2.0)}, "
                         f"within it on {sum(1 for x in ratios if x <= 1.0)}")
    beyond = [f"{Path(r['log']).parent.name}/{Path(r['log']).name}" for r in done if beyond_tune(r)]
    if any(ratio_at(r) is not None for r in done):
        lines.append(f"past what the largest walk guard tune fits allows at {SAY_LAG_S:g} s (a fault or a spoof, not "
                     f"a receiver's usual wander): {len(beyond)} logs{': ' + ', '.join(beyond) if beyond else ''}")
    exps = [r["exponent"] for r in done if "exponent" in r]
    if exps:
        lines.append(f"growth from {SHORT_S:g} to {LONG_S:g} s: T^{statistics.median(exps):.2f} at the median "
                     f"({min(exps):.2f} to {max(exps):.2f}; 0.5 a random walk, 1 a drift) over {len(exps)} logs")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", help="logs, or folders searched for them")
    parser.add_argument("--lags", nargs="+", type=float, default=list(LAGS_S), help="lags T (s)")
    parser.add_argument("--jobs", type=int, default=1, help="logs measured at once")
    parser.add_argument("--json", help="write every figure here")
    parser.add_argument("--config", help="the model of this config's filter (a guard tune profile), not the defaults")
    args = parser.parse_args(argv)
    try:
        load(args.config)
        logs = logs_in(args.paths)
    except GuardError as e:
        print(f"guard: {e}", file=sys.stderr)
        return 1
    jobs = [(log, tuple(args.lags), args.config) for log in logs]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            results = list(pool.map(measure, jobs))
    else:
        results = [measure(j) for j in jobs]
    for r in results:
        print(show(r))
    print("\n".join(summary(results)))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
