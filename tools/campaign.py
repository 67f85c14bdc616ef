"""Monte-Carlo campaign: a scenario over many seeds, replayed through one or more detectors.

    python tools/campaign.py --scenario paper --seeds 20 --detectors cusum paper
    python tools/campaign.py --scenario clean --seeds 3

Each run is simulated to a tlog (cached in --work) and replayed as `guard replay` would. A run
"detects" when an alarm on the attacked sensor comes at or after the first attacked GNSS sample
(its delay, in GNSS samples, counts from that sample); it is "isolated" when the first alarm after
the attack names the attacked sensor. Any alarm before the attack (or any alarm at all in a clean
scenario) is a false alarm. The `paper` detector runs as the paper describes it: it only restarts its test
after an alarm and never stops fusing a sensor (monitor.exclude_on_alarm = false).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from guard.config import parse                  # noqa: E402
from guard.replay import replay                 # noqa: E402
from sim import scenario as scenarios           # noqa: E402
from sim.run import run                         # noqa: E402


def config_for(detector: str):
    table = {"detector": {"name": detector}}
    if detector == "paper":
        table["monitor"] = {"exclude_on_alarm": False}
    return parse(table, f"campaign:{detector}")


def one_run(sc, seed: int, work: Path, detector: str) -> dict:
    tlog = work / f"{sc.name}-{seed}.tlog"
    if not tlog.exists():
        run(sc, seed, tlog=str(tlog))
    truth = json.loads(tlog.with_name(f"{sc.name}-{seed}.truth.json").read_text())
    report = replay(str(tlog), config_for(detector))
    attacks = truth["attacks"]
    k0 = min((a["start_gnss_index"] for a in attacks), default=None)
    sensors = {a["sensor"] for a in attacks}
    alarms = report["alarms"]
    false = [a for a in alarms if k0 is None or a["gnss_index"] < k0]
    hits = [a for a in alarms if k0 is not None and a["gnss_index"] >= k0]
    right = [a for a in hits if a["sensor"] in sensors]
    return {"seed": seed, "false_alarms": len(false), "first": alarms[0] if alarms else None,
            "delay": right[0]["gnss_index"] - k0 if right else None,
            "isolated": bool(right) and right[0] is hits[0], "hours": report["duration_s"] / 3600, "k0": k0}


def summary(sc, detector: str, runs: list[dict]) -> dict:
    delays = sorted(r["delay"] for r in runs if r["delay"] is not None)
    hours = sum(r["hours"] for r in runs)
    fa = sum(r["false_alarms"] for r in runs)
    out = {"scenario": sc.name, "detector": detector, "runs": len(runs), "hours": round(hours, 3),
           "false_alarms": fa, "false_alarms_per_h": round(fa / hours, 2) if hours else None}
    if sc.attacks:
        out.update(detected=len(delays), median_delay=statistics.median(delays) if delays else None,
                   max_delay=max(delays) if delays else None, delays=delays,
                   isolated=sum(r["isolated"] for r in runs))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="paper")
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--detectors", nargs="+", default=["cusum", "paper"])
    p.add_argument("--work", default="out/campaign", help="where tlogs are cached")
    p.add_argument("--json", help="also write the summaries here")
    args = p.parse_args(argv)
    sc = scenarios.load(args.scenario)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    results = []
    for det in args.detectors:
        runs = [one_run(sc, s, work, det) for s in range(args.first_seed, args.first_seed + args.seeds)]
        results.append(summary(sc, det, runs))
        print(json.dumps(results[-1]))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
