"""The harness's metrics over its runs (see tools/eval.py's docstring), and its two figures."""

from __future__ import annotations

import csv
import json
import math
import statistics
from pathlib import Path

import numpy as np


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


def seconds(rs: list[dict], gnss_hz: float) -> list[float]:
    """Each detected run's delay in seconds: its own (a run at its own GNSS rate), else at gnss_hz."""
    return [r["delay_s"] if r.get("delay_s") is not None else r["delay"] / gnss_hz
            for r in rs if r["delay"] is not None]


def vehicle_of(run: dict) -> dict:
    """The run's drawn vehicle (--vehicles), as runs.csv keeps it (JSON) or as a dict; {} without one."""
    car = run.get("vehicle")
    return car if isinstance(car, dict) else json.loads(car) if car else {}


def lorden(size: float, run: dict, arl0_h: float) -> tuple[float, float]:
    """Lorden's asymptotic lower bound ln(ARL0)/I on the mean delay, in GNSS samples, for a step of
    `size` metres on one run (its own innovation variance S and GNSS rate), and that rate. No test
    whose mean time between false alarms is ARL0 can, on average, be faster."""
    hz = float(vehicle_of(run)["gnss_hz"])
    info = size * size / (2 * run["S_pos"])                  # I = nu^2 / (2 S) per GNSS sample
    return math.log(arl0_h * 3600 * hz) / info, hz


# What an attack adds to the innovations' mean, t seconds after its onset, per stream tested (a bias
# integrates: an accelerometer bias b is a velocity b t and a position b t²/2; a gyro bias ω a heading
# ω t; a coordinated spoof accelerating at a moves the GNSS velocity by a t and its position by a t²/2,
# as an accelerometer bias of -a would). Sizes from the case's name. Steps are Lorden's constant shift
# (`lorden`).
SIGNATURES = {
    "ramp": lambda size: (("gnss_pos", lambda t: size * t),),
    "accel": lambda size: (("gnss_vel", lambda t: size * t), ("gnss_pos", lambda t: size * t * t / 2)),
    "gyro": lambda size: (("mag", lambda t: size * t),),
}


def signature(case: str):
    """The case's signature (stream, mean(t)) pairs, or None for a case without one here."""
    words = case.split()
    if words[0] == "ramp" and words[1] in ("north", "east"):
        return SIGNATURES["ramp"](float(words[2]))
    if words[0] in ("accel", "gyro") and words[2] == "bias":
        return SIGNATURES[words[0]](float(words[3]))
    if words[0] == "spoof":             # position and velocity moved together: what no accelerometer felt
        return SIGNATURES["accel"](float(words[2]))
    return None


def information_bound(streams, S: dict, hz: dict, arl0_h: float, horizon_s: float = 120.0) -> float | None:
    """The time after an attack's onset (s) before which no test whose mean time between false alarms
    is arl0_h can expect to have seen enough of it: the least T at which the information its samples
    carry, the sum over each stream's samples t_i <= T of mean(t_i)^2 / (2 S), reaches ln(ARL0), ARL0
    counted in the streams' samples. Lorden's ln(ARL0)/I for a signal that grows, with the known
    onset and shape of an oracle and the innovations white, as the filter's model has them: a lower
    bound, which a filter that follows part of a slow attack does not reach, and which flatters the
    slowest ramps (a receiver's error wanders: a ramp slower than the wander is one more wander). None
    if a stream's S or rate is unknown, or the horizon passes first."""
    if any(S.get(k) is None or not hz.get(k) for k, _ in streams):
        return None
    need = math.log(arl0_h * 3600 * sum(hz[k] for k in {k for k, _ in streams}))
    times = sorted((i / hz[k], k, mean) for k, mean in streams for i in range(1, int(horizon_s * hz[k]) + 1))
    total = 0.0
    for t, k, mean in times:
        total += mean(t) ** 2 / (2 * S[k])
        if total >= need:
            return t
    return None


def growing_bounds(s: dict, rs: list[dict], gnss_hz: float, arl0_h: float) -> None:
    """`information_bound` per run (its own S, GNSS and magnetometer rates) into the summary row s:
    its median and largest (s), and the median of guard's time over it, both counted from the onset
    (guard's alarm's own time; in a campaign from before runs kept it, one GNSS sample after its
    delay, as for the steps)."""
    streams = signature(s["case"])
    if streams is None:
        return
    pairs = []
    for r in rs:
        g = float(vehicle_of(r).get("gnss_hz", gnss_hz))
        b = information_bound(streams, {"gnss_pos": r.get("S_pos"), "gnss_vel": r.get("S_vel"),
                                        "mag": r.get("S_mag")},
                              {"gnss_pos": g, "gnss_vel": g, "mag": r.get("mag_hz")}, arl0_h)
        if b is not None:
            if r["delay"] is None:
                pairs.append((b, None))
            elif r.get("onset_delay_s") is not None:
                pairs.append((b, r["onset_delay_s"]))
            else:                          # a campaign from before the runs kept it: one GNSS sample more
                pairs.append((b, (r["delay_s"] if r.get("delay_s") is not None else r["delay"] / g) + 1 / g))
    if pairs:
        s["information_bound_s"] = statistics.median(b for b, _ in pairs)
        s["information_bound_s_max"] = max(b for b, _ in pairs)
        ratios = [d / b for b, d in pairs if d is not None]
        if ratios:
            s["delay_over_bound"] = statistics.median(ratios)


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
             "median_delay_s": pct(seconds(rs, gnss_hz), 50) if delays else None,
             "p95_delay_s": pct(seconds(rs, gnss_hz), 95) if delays else None,
             "median_onset_delay_s": pct([r["onset_delay_s"] for r in rs if r.get("onset_delay_s") is not None], 50),
             "p95_onset_delay_s": pct([r["onset_delay_s"] for r in rs if r.get("onset_delay_s") is not None], 95),
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
        if family == "step" and any(r.get("vehicle") for r in rs):
            # the second family: each vehicle its own GNSS rate and noise, so its own bound
            size = float(case.split()[2])
            bounds = [lorden(size, r, arl0_samples / (3600 * gnss_hz)) for r in rs if r["S_pos"]]
            s["lorden_bound_s"] = statistics.median(b / hz for b, hz in bounds)
            s["lorden_bound_s_max"] = max(b / hz for b, hz in bounds)
            ratios = [(r["delay"] + 1) / max(b, 1.0) for r, (b, _) in zip([r for r in rs if r["S_pos"]], bounds)
                      if r["delay"] is not None]
            if ratios:
                s["delay_over_lorden"] = statistics.median(ratios)
        elif family in ("ramp", "imu", "spoof"):
            growing_bounds(s, rs, gnss_hz, arl0_samples / (3600 * gnss_hz))
        elif family == "step":
            size = float(case.split()[2])
            S = statistics.median(r["S_pos"] for r in rs if r["S_pos"])
            info = size * size / (2 * S)                      # I = nu^2 / (2 S) per GNSS sample
            s["lorden_bound_samples"] = math.log(arl0_samples) / info
            s["lorden_bound_s"] = s["lorden_bound_samples"] / gnss_hz
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
            pts = sorted((float(s["case"].split()[2]), s["median_delay_s"]) for s in steps
                         if s["detector"] == det and s["median_delay_s"] is not None)
            if pts:
                ax.plot(*zip(*pts), marker="o", label=det)
        bound = sorted({(float(s["case"].split()[2]), s["lorden_bound_s"]) for s in steps})
        ax.plot(*zip(*bound), "k--", label="Lorden bound ln(ARL0)/I" + (" (median vehicle)" if any(
            "lorden_bound_s_max" in s for s in steps) else ""))
        ax.set_xscale("log"); ax.set_yscale("symlog")
        ax.set_xlabel("GNSS north step (m)"); ax.set_ylabel("median delay (s)")
        ax.legend(fontsize=8); fig.tight_layout(); fig.savefig(out / "delay_vs_step.png", dpi=110); plt.close(fig)
