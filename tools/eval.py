"""Evaluation harness: seeded Monte-Carlo campaigns of attack families, replayed through several
detectors side by side. Prints a table and writes CSV, JSON and figures.

    python tools/eval.py                       # the full campaign, 20 seeds (--seeds 10: 8 minutes on 2 cores)
    python tools/eval.py --quick               # a reduced one (a few minutes): what the tests run
    python tools/eval.py --families step ramp --seeds 10 --detectors cusum gate
    python tools/eval.py --figure "gyro z bias 0.05 rad/s" 3   # one run's tlog, report and figure
    python tools/eval.py --figure "step north 10 m" 0 --detectors gate   # ... through another detector
    python tools/eval.py --families imu --set filter.heading_sigma_rad=0.05   # a config key changed
    python tools/eval.py --summarise out/eval-clean       # the table and figures of an earlier campaign again
    python tools/eval.py ... --resume         # an interrupted campaign, on from where it stopped (same code)
    python tools/eval.py --families clean --seeds 300 --first-seed 900   # new noise beside seeds 0..899
    python tools/eval.py --families paper --seeds 20 --detectors cusum paper   # the paper's scenario over seeds
    python tools/eval.py --vehicles --detectors cusum   # every case on vehicles unlike the simulator's defaults

Families (each a list of cases, each case run over --seeds seeds, attack at t = 30 s unless said):
  step      GNSS position step of 1, 2, 5, 10, 20 m on north and east
  ramp      GNSS north drifting at 0.05, 0.1, 0.3, 1, 2 m/s
  spoof     coordinated spoof: north, or east, position and velocity accelerating away at 0.05 m/s^2,
            from 30 s + 9 s x (seed mod 10): along the track or across it, in a turn or a straight
  freeze    the GNSS fix stops updating while the vehicle moves
  imu       gyro z bias 0.05 rad/s; accelerometer x and y bias 0.5 m/s^2; magnetometer x bias 0.05 G and
            x ramp 0.01 G/s (a heading drift, the gyro bias's look-alike: isolation must tell them apart);
            the gyro and accelerometer biases again from 54.5 s, in a turn
  early     a 5 m GNSS north step at GPS sample 5, after a clean start
  clean     10-minute clean drives with turns and speed changes, and others with three 5 s GNSS dropouts
  paper     the paper's scenario (a straight drive, 10 Hz, 10 m on GNSS north from sample 400), not in the default
            set: python tools/eval.py --families paper --seeds 20 --detectors cusum paper gate chi2

Metrics per case and detector: detection rate (any alarm at or after the first attacked sample),
median and 95th-percentile delay (GNSS samples and seconds) from that sample, false alarms per hour
(any alarm before the attack, or in a clean run), the estimate's position error just before the
alarm (what the attack did before it was caught), isolation (the first alarm after the attack names
the attacked sensor alone), ambiguity (it names the attacked sensor among others it cannot tell
apart; what it named is in runs.csv), the estimate's worst position error from the alarm to 30 s
after it (GNSS attacks), and for steps the median delay over the Lorden bound ln(ARL0)/I, I = nu^2 / (2 S);
for the ramps and the gyro and accelerometer biases, which grow, the information bound: the time at
which the sum of mean(t)^2 / (2 S) over the tested samples since the onset reaches ln(ARL0)
(tools/evaluation/summary.py, information_bound), and guard's time over it (delay_over_bound).
For cusum, the largest statistic / threshold of each run (peak_ratio): over the clean runs it is the
threshold's measured margin, and fa_vs_threshold.png shows the share of clean runs that would have
alarmed had every threshold been scaled by a factor (an ROC-like curve, from clean runs only);
extrapolated_fa_interval_h carries that curve's log-linear fit over 0.5..0.85 to the threshold.
The route turns and changes speed (scenario `clean`), GNSS error is 0.3 m white + 0.7 m correlated.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from guard.config import parse, read as read_config   # noqa: E402
from guard.errors import ConfigError             # noqa: E402
from tools.evaluation.cases import (ALL_FAMILIES, START_S, cases, detector_config, phased,  # noqa: E402,F401
                                    sim_seed, vehicle)
from tools.evaluation.figure import figure       # noqa: E402
from tools.evaluation.runs import PARTIAL, Collector, campaign, one   # noqa: E402,F401
from tools.evaluation.summary import extrapolate, plots, read_runs, summarise   # noqa: E402,F401
from guard_sim.scenario import Attack                  # noqa: E402,F401 (the cases are built of these)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--families", nargs="+", default=[f for f in ALL_FAMILIES if f != "paper"], choices=ALL_FAMILIES)
    p.add_argument("--detectors", nargs="+", default=["cusum", "gate", "chi2", "paper"])
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--first-seed", type=int, default=0,
                   help="seeds FIRST .. FIRST+SEEDS-1: more runs on new noise beside an earlier campaign")
    p.add_argument("--quick", action="store_true", help="3 seeds, fewer cases: a few minutes")
    p.add_argument("--vehicles", action="store_true",
                   help="the second noise family: each seed a vehicle whose sensors differ from the defaults "
                   "(tools/evaluation/cases.py: vehicle())")
    p.add_argument("--out", default="out/eval")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="change one config key for every detector (a TOML value: 0.05, '\"air\"')")
    p.add_argument("--config", help="a guard TOML file: its keys apply to every detector, as --set (which wins)")
    p.add_argument("--summarise", metavar="DIR", help="summarise DIR/runs.csv of an earlier campaign again")
    p.add_argument("--resume", action="store_true",
                   help="keep the runs an interrupted campaign left in OUT/runs.partial.jsonl (same code only)")
    p.add_argument("--figure", nargs=2, metavar=("CASE", "SEED"),
                   help="simulate one run; keep its tlog, report, figure (the first of --detectors)")
    args = p.parse_args(argv)
    if args.config:
        try:                                         # guard's own reading and checks: the file and key named
            table, _ = read_config(args.config)
            parse(table, args.config)
        except ConfigError as e:
            print(f"eval: --config {e}", file=sys.stderr)
            return 2
        args.set = [f"{s}.{k}={json.dumps(v)}" for s, t in table.items() for k, v in t.items()] + args.set
    try:                                             # a bad key stops here, named, before any work
        detector_config("cusum", tuple(args.set))
    except (ConfigError, tomllib.TOMLDecodeError) as e:
        print(f"eval: --set: {e}", file=sys.stderr)
        return 2
    if args.figure:
        # one detector: the first of --detectors (cusum unless told)
        return figure(args.figure[0], int(args.figure[1]), Path(args.out), tuple(args.set), args.detectors[0],
                      args.vehicles)
    todo = cases(args.families)
    if args.quick:
        args.seeds = min(args.seeds, 3)
        todo = [c for c in todo if c[0] != "step" or c[1].split()[2] in ("2", "10")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.summarise:
        out = Path(args.summarise)
        if not (out / "runs.csv").is_file():
            print(f"eval: {out / 'runs.csv'}: no such file", file=sys.stderr)
            return 2
        rows = read_runs(out / "runs.csv")
    else:
        with tempfile.TemporaryDirectory() as work:
            # seed by seed, every case within each: what a long campaign has done when it is stopped
            # covers every case alike
            seeds = range(args.first_seed, args.first_seed + args.seeds)
            jobs = [(f, n, a, d, seed, args.detectors, work, tuple(args.set), args.vehicles)
                    for seed in seeds for f, n, a, d in todo]
            if (out / PARTIAL).exists() and not args.resume:
                print(f"eval: {out / PARTIAL} holds the runs of an interrupted campaign: --resume to go on "
                      "with them, or delete it", file=sys.stderr)
                return 2
            rows = campaign(jobs, out, args.jobs, args.resume)
    cfg = detector_config("cusum").monitor.detector
    arl0 = cfg.false_alarm_interval_h * 3600 * 10.0      # in GNSS samples
    summary = summarise(rows, 10.0, arl0)
    with open(out / "runs.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=sorted({k for r in rows for k in r}))
        w.writeheader(); w.writerows(rows)
    (out / PARTIAL).unlink(missing_ok=True)            # the campaign is whole: nothing left to resume
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    plots(summary, rows, out)
    cols = ["case", "detector", "detection_rate", "median_delay_samples", "p95_delay_samples", "median_delay_s",
            "p95_delay_s", "false_alarms_per_h", "isolation_rate", "ambiguous_rate", "p95_error_at_alarm_m",
            "worst_error_30s_after_m", "lorden_bound_s", "delay_over_lorden", "information_bound_s", "delay_over_bound",
            "max_peak_ratio", "extrapolated_fa_interval_h", "named"]
    print(" | ".join(cols))
    for s in summary:
        print(" | ".join("" if s.get(c) is None else (f"{s[c]:.2f}" if isinstance(s[c], float) else
                                                       ", ".join(s[c]) if isinstance(s[c], list) else str(s[c]))
                         for c in cols))
    print(f"(written to {out}/: runs.csv, summary.json, delay_vs_step.png, fa_vs_threshold.png)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
