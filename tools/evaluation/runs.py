"""One run of the harness (simulate, replay through each detector, measure), and a campaign of them
in worker processes."""

from __future__ import annotations

import json
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from guard.core.geo import LocalFrame
from guard.core.monitor import Monitor
from guard.model.events import Alarm, Estimate, Tested
from guard.runtime.pump import Pump
from guard.sinks.base import Sink
from guard.sources.tlog import TlogReader
from guard_sim.run import run
from tools.evaluation.cases import base_scenario, detector_config, phased, sim_seed, vehicle


class Collector(Sink):
    """Keeps what the metrics need from one replay."""

    def __init__(self):
        self.alarms: list[Alarm] = []
        self.estimates: list[tuple[int, float, float]] = []
        self.origin = None
        # each fused test's innovation variance (per channel), for the information bounds of summary.py
        self.S: dict[str, list[float]] = {"gnss_pos": [], "gnss_vel": [], "mag": []}
        self.tested_us: dict[str, list[int]] = {"mag": []}

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Alarm):
                self.alarms.append(e)
            elif isinstance(e, Estimate):
                self.origin = e.origin
                self.estimates.append((e.t_us, e.east_m, e.north_m))
            elif isinstance(e, Tested) and e.innovation.fused and e.innovation.sensor in self.S:
                self.S[e.innovation.sensor].append(float(np.mean(np.diagonal(e.innovation.S))))
                if e.innovation.sensor in self.tested_us:
                    self.tested_us[e.innovation.sensor].append(e.innovation.t_us)

    def S_median(self, sensor: str) -> float | None:
        return statistics.median(self.S[sensor]) if self.S[sensor] else None

    def rate_hz(self, sensor: str) -> float | None:
        """How often the sensor was tested: its rate in the test (the magnetometer comes with the IMU)."""
        t = self.tested_us[sensor]
        return (len(t) - 1) / ((t[-1] - t[0]) * 1e-6) if len(t) > 2 and t[-1] > t[0] else None


def one(job) -> list[dict]:
    """Simulate one case and seed, replay it through every detector; one row per detector."""
    family, name, attacks, duration, seed, detectors, work, settings, *fleet = job
    attacks, duration = phased(family, attacks, duration, seed)
    car = vehicle(seed) if fleet and fleet[0] else None
    sc = base_scenario(family, duration, attacks, car)
    tlog = Path(work) / f"{abs(hash((name, seed)))}.tlog"
    truth = run(sc, sim_seed(family, attacks, seed), tlog=str(tlog))
    real = [a for a in truth["attacks"] if a["kind"] != "dropout"]
    k0 = min((a["start_gnss_index"] for a in real), default=None)
    # an alarm is the attack's from the onset on, though an IMU alarm may come before the first attacked
    # fix (its gnss_index that of the fix before): its delay is then 0 samples, not a false alarm
    t0 = min((a["start_time_usec"] for a in real), default=None)
    sensors = {a["sensor"] for a in real}
    if any(a["kind"] in ("spoof", "freeze") for a in real):
        sensors |= {"gnss_pos", "gnss_vel"}          # they act on the whole fix
    traj = truth["trajectory"]
    rows = []
    for det in detectors:
        cfg = detector_config(det, settings)
        reader, col = TlogReader(str(tlog)), Collector()
        monitor = Monitor(cfg.monitor, date=reader.date)
        Pump(monitor, [col]).run(reader.samples())
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

        false = [a for a in col.alarms if t0 is None or a.t_us < t0]
        after = [a for a in col.alarms if t0 is not None and a.t_us >= t0]
        right = [a for a in after if a.sensor in sensors or sensors & set(a.ambiguous_with)]
        row = {"family": family, "case": name, "seed": seed, "detector": det, "hours": duration / 3600,
               "false_alarms": len(false), "detected": bool(after),
               "delay": max(0, after[0].gnss_index - k0) if after else None,
               "delay_s": max(0, after[0].gnss_index - k0) / sc.rates.gnss_hz if after else None,
               # from the onset in time: an IMU alarm's own moment, not the GNSS sample it fell after
               "onset_delay_s": (after[0].t_us - t0) / 1e6 if after else None,
               "vehicle": json.dumps(car) if car else None,
               "isolated": bool(right) and right[0] is after[0] and not right[0].ambiguous_with,
               "ambiguous": bool(right) and right[0] is after[0] and bool(right[0].ambiguous_with),
               "first_sensor": "|".join((after[0].sensor, *after[0].ambiguous_with)) + f" {after[0].channel}"
               if after else None,
               "error_at_alarm_m": error_at(after[0].t_us, before=True) if after else None,
               "S_pos": col.S_median("gnss_pos"), "S_vel": col.S_median("gnss_vel"),
               "S_mag": col.S_median("mag"), "mag_hz": col.rate_hz("mag"),
               "peak_ratio": max(monitor.detector.peak.values(), default=None)}
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
        family, name, _, _, seed, detectors, _, settings, *fleet = job
        return json.dumps([family, name, seed, list(detectors), list(settings), *fleet])
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
