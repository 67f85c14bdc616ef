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

Families (each a list of cases, each case run over --seeds seeds, attack at t = 30 s unless said):
  step      GNSS position step of 1, 2, 5, 10, 20 m on north and east
  ramp      GNSS north drifting at 0.05, 0.1, 0.3, 1, 2 m/s
  spoof     coordinated spoof: north, or east, position and velocity accelerating away at 0.05 m/s^2,
            from 30 s + 9 s x (seed mod 10): along the track or across it, in a turn or a straight
  freeze    the GNSS fix stops updating while the vehicle moves
  imu       gyro z bias 0.05 rad/s; accelerometer x and y bias 0.5 m/s^2; magnetometer x bias 0.05 G and
            x ramp 0.01 G/s (a heading drift, the gyro bias's look-alike: isolation must tell them apart)
  early     a 5 m GNSS north step at GPS sample 5, after a clean start
  clean     10-minute clean drives with turns and speed changes, and others with three 5 s GNSS dropouts

Metrics per case and detector: detection rate (any alarm at or after the first attacked sample),
median and 95th-percentile delay (GNSS samples and seconds) from that sample, false alarms per hour
(any alarm before the attack, or in a clean run), the estimate's position error just before the
alarm (what the attack did before it was caught), isolation (the first alarm after the attack names
the attacked sensor alone), ambiguity (it names the attacked sensor among others it cannot tell
apart; what it named is in runs.csv), the estimate's worst position error from the alarm to 30 s
after it (GNSS attacks), and for steps the median delay over the Lorden bound ln(ARL0)/I, I = nu^2 / (2 S).
For cusum, the largest statistic / threshold of each run (peak_ratio): over the clean runs it is the
threshold's measured margin, and fa_vs_threshold.png shows the share of clean runs that would have
alarmed had every threshold been scaled by a factor (an ROC-like curve, from clean runs only);
extrapolated_fa_interval_h carries that curve's log-linear fit over 0.5..0.85 to the threshold.
The route turns and changes speed (scenario `clean`), GNSS error is 0.3 m white + 0.7 m correlated.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import statistics
import sys
import tempfile
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np                               # noqa: E402

from guard.config import parse, read as read_config   # noqa: E402
from guard.core import Monitor                   # noqa: E402
from guard.errors import ConfigError             # noqa: E402
from guard.events import Alarm, Estimate, Tested  # noqa: E402
from guard.geo import LocalFrame                 # noqa: E402
from guard.mavlink import TlogReader, tlog_samples   # noqa: E402
from sim import scenario as scenarios            # noqa: E402
from sim.run import run                          # noqa: E402
from sim.scenario import Attack                  # noqa: E402

START_S = 30.0
SPOOF_PHASE_S = 9.0


def cases(families: list[str]) -> list[tuple[str, str, tuple[Attack, ...], float]]:
    """(family, case name, attacks, duration_s)."""
    out = []
    if "step" in families:
        for ch in ("north", "east"):
            for m in (1.0, 2.0, 5.0, 10.0, 20.0):
                out.append(("step", f"step {ch} {m:g} m", (Attack("step", "gnss_pos", ch, m, START_S),), 60.0))
    if "ramp" in families:
        for m in (0.05, 0.1, 0.3, 1.0, 2.0):
            out.append(("ramp", f"ramp north {m:g} m/s", (Attack("ramp", "gnss_pos", "north", m, START_S),), 90.0))
    if "spoof" in families:
        for ch in ("north", "east"):
            out.append(("spoof", f"spoof {ch} 0.05 m/s2", (Attack("spoof", "gnss_pos", ch, 0.05, START_S),), 105.0))
    if "freeze" in families:
        out.append(("freeze", "freeze", (Attack("freeze", "gnss_pos", "north", 0.0, START_S),), 60.0))
    if "imu" in families:
        out.append(("imu", "gyro z bias 0.05 rad/s", (Attack("bias", "gyro", "z", 0.05, START_S),), 60.0))
        out.append(("imu", "accel x bias 0.5 m/s2", (Attack("bias", "accel", "x", 0.5, START_S),), 60.0))
        out.append(("imu", "accel y bias 0.5 m/s2", (Attack("bias", "accel", "y", 0.5, START_S),), 60.0))
        out.append(("imu", "mag x bias 0.05 G", (Attack("bias", "mag", "x", 0.05, START_S),), 60.0))
        out.append(("imu", "mag x ramp 0.01 G/s", (Attack("ramp", "mag", "x", 0.01, START_S),), 60.0))
    if "early" in families:
        out.append(("early", "step north 5 m at sample 5", (Attack("step", "gnss_pos", "north", 5.0, 0.5),), 40.0))
    if "clean" in families:
        out.append(("clean", "clean 10 min", (), 600.0))
        drops = tuple(Attack("dropout", "gnss_pos", "north", 0.0, t, 5.0) for t in (60.0, 200.0, 400.0))
        out.append(("clean", "clean 10 min, GNSS dropouts", drops, 600.0))
    return out


def sim_seed(family: str, attacks: tuple, seed: int) -> int:
    """The simulator's seed for a campaign's seed: the same for every attack case (their differences
    are the attacks', not the noise's); the clean drives even, the ones with dropouts odd, so that
    every clean hour is a distinct one."""
    return 2 * seed + bool(attacks) if family == "clean" else seed


def phased(family: str, attacks: tuple, duration: float, seed: int) -> tuple[tuple, float]:
    """A spoof's physics depends on where the vehicle is on its route (along the track it looks like
    an accelerometer bias until a turn): its start moves 9 s a seed, over the route's first 81 s."""
    if family != "spoof":
        return attacks, duration
    shift = SPOOF_PHASE_S * (seed % 10)
    return tuple(dataclasses.replace(a, start_s=a.start_s + shift) for a in attacks), duration + shift


def detector_config(name: str, settings: tuple[str, ...] = ()):
    """guard's defaults with `settings` ("section.key=TOML value") applied, and the named detector."""
    table: dict = {"detector": {"name": name}}
    if name == "paper":      # as the paper describes it: restart the test, never stop fusing
        table["monitor"] = {"exclude_on_alarm": False}
    for item in settings:
        key, _, value = item.partition("=")
        section, _, field = key.strip().partition(".")
        table.setdefault(section, {})[field] = tomllib.loads(f"v = {value}")["v"]
    return parse(table, f"eval:{name} {' '.join(settings)}")


class Collector:
    """Keeps what the metrics need from one replay."""

    def __init__(self):
        self.alarms: list[Alarm] = []
        self.estimates: list[tuple[int, float, float]] = []
        self.origin = None
        self.S_pos: list[float] = []

    def take(self, events) -> None:
        for e in events:
            if isinstance(e, Alarm):
                self.alarms.append(e)
            elif isinstance(e, Estimate):
                self.origin = e.origin
                self.estimates.append((e.t_us, e.east_m, e.north_m))
            elif isinstance(e, Tested) and e.innovation.sensor == "gnss_pos" and e.innovation.fused:
                self.S_pos.append(float(np.mean(np.diagonal(e.innovation.S))))


def one(job) -> list[dict]:
    """Simulate one case and seed, replay it through every detector; one row per detector."""
    family, name, attacks, duration, seed, detectors, work, settings = job
    attacks, duration = phased(family, attacks, duration, seed)
    base = scenarios.load("clean")
    sc = dataclasses.replace(base, name="eval", duration_s=duration, attacks=attacks)
    tlog = Path(work) / f"{abs(hash((name, seed)))}.tlog"
    truth = run(sc, sim_seed(family, attacks, seed), tlog=str(tlog))
    real = [a for a in truth["attacks"] if a["kind"] != "dropout"]
    k0 = min((a["start_gnss_index"] for a in real), default=None)
    sensors = {a["sensor"] for a in real}
    if any(a["kind"] in ("spoof", "freeze") for a in real):
        sensors |= {"gnss_pos", "gnss_vel"}          # they act on the whole fix
    traj = truth["trajectory"]
    rows = []
    for det in detectors:
        cfg = detector_config(det, settings)
        reader, col = TlogReader(str(tlog)), Collector()
        monitor = Monitor(cfg.monitor, date=reader.date)
        for sample in tlog_samples(reader):
            col.take(monitor.step(sample))
        col.take(monitor.finish())
        reader.close()
        frame = LocalFrame(*col.origin)
        true_en = np.array([frame.to_en(a, b) for a, b in zip(traj["lat_deg"], traj["lon_deg"])])
        t_true = np.array(traj["t_usec"], dtype=float)
        est = np.array(col.estimates, dtype=float)

        def error_at(t_us: float, before: bool = False) -> float:
            """Error of the estimate at t_us (or of the last one before it: what the attack did before
            the alarm, which guard's rewind then undoes in the estimate at the alarm)."""
            i = int(np.searchsorted(est[:, 0], t_us)) - before
            i = min(max(i, 0), len(est) - 1)
            j = min(int(np.searchsorted(t_true, est[i, 0])), len(t_true) - 1)
            return float(np.hypot(*(est[i, 1:] - true_en[j])))

        false = [a for a in col.alarms if k0 is None or a.gnss_index < k0]
        after = [a for a in col.alarms if k0 is not None and a.gnss_index >= k0]
        right = [a for a in after if a.sensor in sensors or sensors & set(a.ambiguous_with)]
        row = {"family": family, "case": name, "seed": seed, "detector": det, "hours": duration / 3600,
               "false_alarms": len(false), "detected": bool(after),
               "delay": after[0].gnss_index - k0 if after else None,
               "isolated": bool(right) and right[0] is after[0] and not right[0].ambiguous_with,
               "ambiguous": bool(right) and right[0] is after[0] and bool(right[0].ambiguous_with),
               "first_sensor": "|".join((after[0].sensor, *after[0].ambiguous_with)) + f" {after[0].channel}"
               if after else None,
               "error_at_alarm_m": error_at(after[0].t_us, before=True) if after else None,
               "S_pos": statistics.median(col.S_pos) if col.S_pos else None,
               "peak_ratio": max(getattr(monitor.detector, "peak", {}).values(), default=None)}
        if after and family in ("step", "ramp", "spoof", "freeze", "early"):
            t_a = after[0].t_us
            window = est[(est[:, 0] >= t_a) & (est[:, 0] <= t_a + 30e6)]
            row["error_30s_after_m"] = max((error_at(t) for t in window[:, 0]), default=None)
        rows.append(row)
    tlog.unlink()
    tlog.with_name(tlog.name[:-5] + ".truth.json").unlink()
    return rows


PARTIAL = "runs.partial.jsonl"     # the rows of a campaign still running, one finished job a line


def campaign(jobs: list[tuple], out: Path, workers: int, resume: bool) -> list[dict]:
    """Run the jobs in parallel; say how far it got every ~5 %. Each finished job's rows are appended
    to out/runs.partial.jsonl at once, so that an interrupted campaign resumes (`resume`) where it
    stopped: jobs with the same case, seed, detectors and settings are not run again. Rows come back
    in the jobs' order, whatever order the workers finish in."""
    def key(job):
        family, name, _, _, seed, detectors, _, settings = job
        return json.dumps([family, name, seed, list(detectors), list(settings)])
    done: dict[str, list[dict]] = {}
    partial = out / PARTIAL
    if resume and partial.is_file():
        for line in partial.read_text().splitlines():
            try:
                item = json.loads(line)
                done[item["key"]] = item["rows"]
            except (json.JSONDecodeError, KeyError, TypeError):
                pass                                  # a line cut by the interruption: that job runs again
    # what was kept, whole lines only (a cut last line would swallow the next one appended)
    partial.write_text("".join(json.dumps({"key": k, "rows": rows}) + "\n" for k, rows in done.items()))
    todo = [job for job in jobs if key(job) not in done]
    if done:
        print(f"eval: resuming: {len(jobs) - len(todo)} of {len(jobs)} runs already in {partial}", file=sys.stderr)
    t0, step = time.monotonic(), max(1, len(todo) // 20)
    with ProcessPoolExecutor(max_workers=workers) as pool, open(partial, "a") as log:
        futures = {pool.submit(one, job): key(job) for job in todo}
        try:
            for i, fut in enumerate(as_completed(futures), 1):
                done[futures[fut]] = rows = fut.result()
                log.write(json.dumps({"key": futures[fut], "rows": rows}) + "\n")
                log.flush()
                if i % step == 0 or i == len(todo):
                    left = (time.monotonic() - t0) / i * (len(todo) - i)
                    print(f"eval: {i} of {len(todo)} runs done, about {left / 60:.0f} min left", file=sys.stderr,
                          flush=True)
        except BaseException:           # a failed run or Ctrl-C: stop now; what finished is kept for --resume
            pool.shutdown(wait=False, cancel_futures=True)
            raise
    return [r for job in jobs for r in done[key(job)]]


def pct(values, q):
    return float(np.percentile(values, q)) if values else None


def extrapolate(rs: list[dict]) -> float | None:
    """Hours per false alarm at guard's threshold, extrapolated from clean runs: the rate of runs whose
    peak statistic/threshold reaches a scale m, fitted log-linearly over m = 0.5 .. 0.85, at m = 1.
    An extrapolation of the tail, not a measurement; None unless 3 runs reach each of 3 scales or more."""
    peaks = np.array([r["peak_ratio"] for r in rs if r["peak_ratio"] is not None])
    hours = sum(r["hours"] for r in rs if r["peak_ratio"] is not None)
    # a scale counts when at least 3 runs reach it: a rate from one or two runs is noise
    pts = [(m, (peaks >= m).sum() / hours) for m in np.arange(0.5, 0.851, 0.05) if (peaks >= m).sum() >= 3]
    if len(pts) < 3:
        return None
    a, b = np.polyfit([m for m, _ in pts], [math.log10(rate) for _, rate in pts], 1)
    return float(10.0 ** -(a + b))


def read_runs(path: Path) -> list[dict]:
    """runs.csv of an earlier campaign, typed back: numbers, booleans and empty fields (None)."""
    def typed(v: str):
        if v in ("", "None"):
            return None
        if v in ("True", "False"):
            return v == "True"
        try:
            return int(v)
        except ValueError:
            try:
                return float(v)
            except ValueError:
                return v
    with open(path, newline="") as f:
        return [{k: typed(v) for k, v in row.items()} for row in csv.DictReader(f)]


def summarise(rows: list[dict], gnss_hz: float, arl0_samples: float) -> list[dict]:
    out = []
    keys = sorted({(r["family"], r["case"], r["detector"]) for r in rows}, key=lambda k: (k[0], k[1], k[2]))
    for family, case, det in keys:
        rs = [r for r in rows if (r["family"], r["case"], r["detector"]) == (family, case, det)]
        delays = [r["delay"] for r in rs if r["delay"] is not None]
        hours = sum(r["hours"] for r in rs)
        s = {"family": family, "case": case, "detector": det, "runs": len(rs),
             "detection_rate": sum(r["detected"] for r in rs) / len(rs) if family != "clean" else None,
             "median_delay_samples": pct(delays, 50), "p95_delay_samples": pct(delays, 95),
             "median_delay_s": pct(delays, 50) / gnss_hz if delays else None,
             "p95_delay_s": pct(delays, 95) / gnss_hz if delays else None,
             "false_alarms_per_h": sum(r["false_alarms"] for r in rs) / hours,
             "isolation_rate": (sum(r["isolated"] for r in rs) / max(1, sum(r["detected"] for r in rs)))
             if delays else None,
             "ambiguous_rate": (sum(r["ambiguous"] for r in rs) / max(1, sum(r["detected"] for r in rs)))
             if delays else None,
             "median_error_at_alarm_m": pct([r["error_at_alarm_m"] for r in rs if r["detected"]], 50),
             "p95_error_at_alarm_m": pct([r["error_at_alarm_m"] for r in rs if r["detected"]], 95),
             "named": sorted({r["first_sensor"] for r in rs if r["first_sensor"]}),
             "worst_error_30s_after_m": max((r.get("error_30s_after_m") or 0.0 for r in rs), default=None),
             "clean_hours": hours if family == "clean" else None,
             "max_peak_ratio": max((r["peak_ratio"] for r in rs if r["peak_ratio"] is not None), default=None)
             if family == "clean" else None,
             "extrapolated_fa_interval_h": extrapolate(rs) if family == "clean" else None}
        if family == "step":
            size = float(case.split()[2])
            S = statistics.median(r["S_pos"] for r in rs if r["S_pos"])
            info = size * size / (2 * S)                      # I = nu^2 / (2 S) per GNSS sample
            s["lorden_bound_samples"] = math.log(arl0_samples) / info
            if delays:
                # delay counted from the first attacked sample: an alarm on it is one sample of data
                s["delay_over_lorden"] = (statistics.median(delays) + 1) / max(s["lorden_bound_samples"], 1.0)
        out.append(s)
    return out


def plots(summary: list[dict], rows: list[dict], out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    clean = [r for r in rows if r["family"] == "clean" and r["peak_ratio"] is not None]
    if clean:
        peaks = np.array([r["peak_ratio"] for r in clean])
        hours = sum(r["hours"] for r in clean)
        scale = np.linspace(0.2, 1.5, 131)
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.plot(scale, [(peaks >= m).sum() / hours for m in scale], label=f"cusum, {hours:.0f} clean hours")
        ax.axvline(1.0, color="k", ls="--", label="guard's threshold")
        ax.set_yscale("symlog", linthresh=0.01)
        ax.set_ylim(bottom=0.0)
        ax.set_xlabel("threshold scale (1 = set from the target interval)")
        ax.set_ylabel("clean runs alarmed per hour (a lower bound)")
        ax.legend(fontsize=8); fig.tight_layout(); fig.savefig(out / "fa_vs_threshold.png", dpi=110); plt.close(fig)
    steps = [s for s in summary if s["family"] == "step" and "north" in s["case"]]
    if steps:
        fig, ax = plt.subplots(figsize=(6, 4))
        for det in sorted({s["detector"] for s in steps}):
            pts = sorted((float(s["case"].split()[2]), s["median_delay_samples"]) for s in steps
                         if s["detector"] == det and s["median_delay_samples"] is not None)
            if pts:
                ax.plot(*zip(*pts), marker="o", label=det)
        bound = sorted({(float(s["case"].split()[2]), s["lorden_bound_samples"]) for s in steps})
        ax.plot(*zip(*bound), "k--", label="Lorden bound ln(ARL0)/I")
        ax.set_xscale("log"); ax.set_yscale("symlog")
        ax.set_xlabel("GNSS north step (m)"); ax.set_ylabel("median delay (GNSS samples)")
        ax.legend(fontsize=8); fig.tight_layout(); fig.savefig(out / "delay_vs_step.png", dpi=110); plt.close(fig)


def figure(case: str, seed: int, out: Path, settings: tuple[str, ...] = (), detector: str = "cusum") -> int:
    """One run of one case: its tlog and truth, the replay report (`detector`, with `settings`) and
    the three-panel figure."""
    from guard.plot import plot
    from guard.replay import Trace, replay, write_report
    found = [c for c in cases(["step", "ramp", "spoof", "freeze", "imu", "early", "clean"]) if c[1] == case]
    if not found:
        print(f"eval: no case {case!r}; the cases are: " + "; ".join(c[1] for c in cases(
            ["step", "ramp", "spoof", "freeze", "imu", "early", "clean"])), file=sys.stderr)
        return 2
    family, name, attacks, duration = found[0]
    attacks, duration = phased(family, attacks, duration, seed)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{name.replace(' ', '_').replace('/', '_')}-seed{seed}"
    sc = dataclasses.replace(scenarios.load("clean"), name="eval", duration_s=duration, attacks=attacks)
    truth = run(sc, sim_seed(family, attacks, seed), tlog=f"{stem}.tlog")
    trace = Trace()
    report = replay(f"{stem}.tlog", detector_config(detector, settings), listeners=(trace,))
    write_report(report, f"{stem}.json")
    plot(trace, report, f"{stem}.png", truth)
    first = report["alarms"][0] if report["alarms"] else None
    print(f"{stem}.tlog, .json, .png: " + (f"first alarm at GNSS sample {first['gnss_index']} "
          f"({'|'.join([first['sensor'], *first['ambiguous_with']])} {first['channel']})" if first else "no alarm"))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--families", nargs="+", default=["step", "ramp", "spoof", "freeze", "imu", "early", "clean"])
    p.add_argument("--detectors", nargs="+", default=["cusum", "gate", "chi2", "paper"])
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--first-seed", type=int, default=0,
                   help="seeds FIRST .. FIRST+SEEDS-1: more runs on new noise beside an earlier campaign")
    p.add_argument("--quick", action="store_true", help="3 seeds, fewer cases: a few minutes")
    p.add_argument("--out", default="out/eval")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="change one config key for every detector (a TOML value: 0.05, '\"air\"')")
    p.add_argument("--config", help="a guard TOML file: its keys apply to every detector, as --set (which wins)")
    p.add_argument("--summarise", metavar="DIR", help="summarise DIR/runs.csv of an earlier campaign again")
    p.add_argument("--resume", action="store_true",
                   help="keep the runs an interrupted campaign left in OUT/runs.partial.jsonl (same code only)")
    p.add_argument("--figure", nargs=2, metavar=("CASE", "SEED"), help="simulate one run; keep its tlog, report, figure (the first of --detectors)")
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
        return figure(args.figure[0], int(args.figure[1]), Path(args.out), tuple(args.set), args.detectors[0])
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
            jobs = [(f, n, a, d, seed, args.detectors, work, tuple(args.set)) for seed in seeds for f, n, a, d in todo]
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
            "p95_delay_s", "false_alarms_per_h", "isolation_rate", "ambiguous_rate", "p95_error_at_alarm_m", "worst_error_30s_after_m",
            "delay_over_lorden", "max_peak_ratio", "extrapolated_fa_interval_h", "named"]
    print(" | ".join(cols))
    for s in summary:
        print(" | ".join("" if s.get(c) is None else (f"{s[c]:.2f}" if isinstance(s[c], float) else
                                                       ", ".join(s[c]) if isinstance(s[c], list) else str(s[c]))
                         for c in cols))
    print(f"(written to {out}/: runs.csv, summary.json, delay_vs_step.png, fa_vs_threshold.png)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
