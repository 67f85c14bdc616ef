"""The paper's three panels for one replay: position estimation error, measurement error (both need
the simulator's truth; without it, the estimate and the measurement themselves), on the axis of the
channel shown, and that channel's test statistic with its threshold; alarms, exclusions, the attack
and the autopilot's verdicts marked, each in a legend (`plot`)."""

from __future__ import annotations

import numpy as np

from guard.core.geo import LocalFrame
from guard.model.events import Estimate, Tested
from guard.model.samples import GnssFix
from guard.sinks.base import Sink


class Trace(Sink):
    """Per-sample series kept for a figure: estimate, measurement, statistics of every channel."""

    def __init__(self):
        self.gnss: list[tuple[int, float, float]] = []        # (t_us, lat, lon) of fixes
        self.estimate: list[tuple[int, float, float]] = []    # (t_us, east, north)
        self.origin: tuple[float, float, float] | None = None
        self.stats: dict[tuple[str, str], list[tuple[int, float, float]]] = {}

    def on_sample(self, sample) -> None:
        if isinstance(sample, GnssFix) and sample.fix_ok:
            self.gnss.append((sample.t_us, sample.lat_deg, sample.lon_deg))

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Tested):
                for name, g, h in zip(e.innovation.channels, e.statistic, e.threshold):
                    self.stats.setdefault((e.innovation.sensor, name), []).append((e.innovation.t_us, g, h))
            elif isinstance(e, Estimate):
                self.origin = e.origin
                self.estimate.append((e.t_us, e.east_m, e.north_m))


def shown_channel(trace: Trace, report: dict) -> tuple[str, str]:
    """The (sensor, channel) the figure is about: the first alarm's, where it has a test of its own;
    else (a freeze, a gyro named by the heading's witnesses, a clean log) the channel that came
    nearest its threshold."""
    alarms = report["alarms"]
    if alarms and (alarms[0]["sensor"], alarms[0]["channel"]) in trace.stats:
        return alarms[0]["sensor"], alarms[0]["channel"]
    if not trace.stats:
        return "gnss_pos", "north"
    return max(trace.stats, key=lambda k: max((g / h for _, g, h in trace.stats[k] if h > 0), default=0.0))


def exclusions(report: dict, t_end_us: int) -> list[tuple[int, int, str]]:
    """(start, end, sensor) of each time a sensor was out of the filter: from its alarm to its
    re-admission (or the end of the log)."""
    out = []
    for a in report["alarms"]:
        back = [c["time_usec"] for c in report["cleared"]
                if c["sensor"] == a["sensor"] and c["time_usec"] >= a["time_usec"]]
        end = min(back, default=t_end_us)
        if not any(s == a["sensor"] and s0 <= a["time_usec"] <= e for s0, e, s in out):
            out.append((a["time_usec"], end, a["sensor"]))
    return out


def plot(trace: Trace, report: dict, out: str, truth: dict | None = None) -> None:
    """Three panels over time since the first fix: the estimate's error (or the estimate and the GNSS)
    on the axis of the channel shown, the GNSS's error (or GNSS minus the estimate) on it, and that
    channel's test statistic against its threshold. Shaded: the attack (the simulator's truth, where
    it is beside the log), the sensor's exclusion, the autopilot's own EKF verdicts; every mark is in
    a legend. A log without an alarm shows the channel nearest its threshold and its margin."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 8.5), sharex=True)
    if not trace.estimate or trace.origin is None:
        axes[0].set_title("no GNSS fix in this log: nothing to plot")
        fig.savefig(out, dpi=110)
        plt.close(fig)
        return
    frame = LocalFrame(*trace.origin)
    t0 = trace.estimate[0][0]
    key = shown_channel(trace, report)
    axis = 1 if key[1] != "east" else 0                     # the position axis shown: east or north
    name = ("east", "north")[axis]
    est = np.array(trace.estimate, dtype=float)
    t_est, p_est = (est[:, 0] - t0) / 1e6, est[:, 1 + axis]
    meas = np.array([(t, *frame.to_en(lat, lon)) for t, lat, lon in trace.gnss], dtype=float)
    t_meas, p_meas = (meas[:, 0] - t0) / 1e6, meas[:, 1 + axis]
    if truth and truth.get("trajectory", {}).get("t_usec"):
        tr = truth["trajectory"]
        t_true = (np.array(tr["t_usec"], dtype=float) - t0) / 1e6
        p_true = np.array([frame.to_en(a, b)[axis] for a, b in zip(tr["lat_deg"], tr["lon_deg"])])
        axes[0].plot(t_est, p_est - np.interp(t_est, t_true, p_true), lw=0.8, label="guard's estimate minus the truth")
        axes[0].set_ylabel(f"{name} estimation\nerror (m)")
        axes[1].plot(t_meas, p_meas - np.interp(t_meas, t_true, p_true), lw=0.8, color="tab:orange",
                     label="GNSS minus the truth")
        axes[1].set_ylabel(f"{name} measurement\nerror (m)")
    else:
        axes[0].plot(t_est, p_est, lw=0.8, label="guard's estimate")
        axes[0].plot(t_meas, p_meas, lw=0.6, label="GNSS")
        axes[0].set_ylabel(f"{name} (m)")
        axes[1].plot(t_meas, p_meas - np.interp(t_meas, t_est, p_est), lw=0.8, color="tab:orange",
                     label="GNSS minus the estimate")
        axes[1].set_ylabel(f"{name} GNSS minus\nestimate (m)")
    series = np.array(trace.stats.get(key, []), dtype=float)
    if len(series):
        axes[2].plot((series[:, 0] - t0) / 1e6, series[:, 1], lw=0.8, label=f"{report['detector']} statistic")
        axes[2].plot((series[:, 0] - t0) / 1e6, series[:, 2], lw=0.8, ls="--", color="k",
                     label="threshold of the test nearest it (CUSUM bank: it steps when the\n"
                     "small-shift and large-shift members take turns)")
    alarms = report["alarms"]
    labels = set()

    def once(label: str) -> dict:
        """A legend entry the first time a kind of mark is drawn."""
        if label in labels:
            return {}
        labels.add(label)
        return {"label": label}

    t_end = int(max(est[-1, 0], meas[-1, 0] if len(meas) else 0))
    for start, end, sensor in exclusions(report, t_end):
        for i, ax in enumerate(axes):
            ax.axvspan((start - t0) / 1e6, (end - t0) / 1e6, color="tab:red", alpha=0.08,
                       **(once(f"{sensor} excluded (alarm to re-admission)") if i == 2 else {}))
    for a in alarms:
        mine = (a["sensor"], a["channel"]) == key
        label = f"guard alarm: {key[0]} {key[1]}" if mine else "guard alarm: another sensor or axis"
        for i, ax in enumerate(axes):
            ax.axvline((a["time_usec"] - t0) / 1e6, color="r", lw=1.0 if mine else 0.5,
                       **(once(label) if i == 2 else {}))
    for a in (truth or {}).get("attacks", []):
        start = (a["start_time_usec"] - t0) / 1e6
        end = (t_end - t0) / 1e6 if a["duration_s"] == "end" else start + a["duration_s"]
        what = "GNSS dropout" if a["kind"] == "dropout" else f"attack: {a['kind']} on {a['sensor']} {a['channel']}"
        for i, ax in enumerate(axes):
            ax.axvspan(start, end, color="grey", alpha=0.12, **(once(f"{what} (simulator's truth)") if i == 2 else {}))
    # the autopilot's own verdict, where the log holds it: its EKF's test ratios over 1 (shaded) and
    # its GNSS messages (ticks), beside guard's alarms
    for v in report.get("autopilot", []):
        start = (v["time_usec"] - t0) / 1e6
        label = f"autopilot: {v['source']} {v['test']} over 1" if v.get("end_usec") else "autopilot: GPS message"
        if v.get("end_usec"):
            axes[2].axvspan(start, max((v["end_usec"] - t0) / 1e6, start + 0.2), color="tab:purple", alpha=0.2,
                            **once(label))
        else:
            axes[2].axvline(start, color="tab:purple", lw=0.8, ls="-.", **once(label))
    axes[2].set_ylabel(f"test of {key[0]} {key[1]}")
    axes[2].set_yscale("symlog")
    axes[2].set_xlabel("time since first fix (s)")
    for ax in axes:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", fontsize=7, framealpha=0.8)
    peak = max((g / h for _, g, h in trace.stats.get(key, []) if h > 0), default=None)
    if alarms:
        a0 = alarms[0]
        verdict = (f"{len(alarms)} alarm(s), the first at GNSS sample {a0['gnss_index']} "
                   f"({a0['sensor']} {a0['channel']})")
    else:
        verdict = "no alarm" + (f": the nearest test, {key[0]} {key[1]}, reached {peak:.2f} of its threshold"
                                if peak is not None else "")
    fig.suptitle(f"{report['source'].rsplit('/', 1)[-1]}: {verdict}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
