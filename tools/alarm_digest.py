"""Every alarm of the harness's quick campaign and of the paper scenario, for every detector, to the
sample and the statistic: what a change that should not change behaviour (a move, a refactor) must
leave identical.

    python tools/alarm_digest.py before.json            # on the code before the change
    python tools/alarm_digest.py after.json --compare before.json   # after it: any difference is listed

The quick campaign's cases (tools/eval.py --quick: its step sizes 2 and 10 m, every other family) and
the paper scenario, seeds 0-2, simulated once into --work and replayed through cusum, gate, chi2 and
paper. A run's digest is its alarms as (GNSS sample, sensor, channel, statistic to 9 digits).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from guard.runtime.replay import replay               # noqa: E402
from guard_sim import scenario as scenarios                  # noqa: E402
from guard_sim.run import run                                # noqa: E402
from tools.evaluation.cases import ALL_FAMILIES, base_scenario, cases, detector_config, phased, sim_seed   # noqa: E402

DETECTORS = ("cusum", "gate", "chi2", "paper")


def logs(work: Path) -> list[Path]:
    """The runs' tlogs, simulated into `work` unless already there (the simulator is not under test)."""
    todo = [c for c in cases([f for f in ALL_FAMILIES if f != "paper"])
            if c[0] != "step" or c[1].split()[2] in ("2", "10")]
    out = []
    for seed in range(3):
        for family, name, attacks, duration in todo:
            path = work / f"{family}-{name.replace(' ', '_').replace('/', '')}-{seed}.tlog"
            if not path.exists():
                a, d = phased(family, attacks, duration, seed)
                run(base_scenario(family, d, a), sim_seed(family, attacks, seed), tlog=str(path))
            out.append(path)
        path = work / f"paper-{seed}.tlog"
        if not path.exists():
            run(scenarios.load("paper"), seed, tlog=str(path))
        out.append(path)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="the digest to write (JSON)")
    p.add_argument("--work", default="out/digest-logs", help="where the simulated tlogs are kept")
    p.add_argument("--compare", help="an earlier digest: list the runs whose alarms differ")
    args = p.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    digest = {}
    for path in logs(work):
        for det in DETECTORS:
            report = replay(str(path), detector_config(det))
            digest[f"{path.name} {det}"] = [[a["gnss_index"], a["sensor"], a["channel"], round(a["statistic"], 9)]
                                            for a in report["alarms"]]
    Path(args.out).write_text(json.dumps(digest, indent=0, sort_keys=True))
    print(f"{len(digest)} runs, {sum(len(v) for v in digest.values())} alarms -> {args.out}")
    if args.compare:
        before = json.loads(Path(args.compare).read_text())
        differ = sorted(k for k in before.keys() | digest.keys() if before.get(k) != digest.get(k))
        print(f"{len(differ)} runs differ from {args.compare}" + "".join(f"\n  {k}" for k in differ[:20]))
        return 1 if differ else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
