"""The paper's three panels for one replay: north position estimation error, north measurement
error (both need the simulator's truth; without it, the estimate and the measurement themselves),
and the test statistic with its threshold, the alarm and the attack marked."""

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


def plot(trace: Trace, report: dict, out: str, truth: dict | None = None) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    if not trace.estimate or trace.origin is None:
        axes[0].set_title("no GNSS fix in this log: nothing to plot")
        fig.savefig(out, dpi=110)
        plt.close(fig)
        return
    frame = LocalFrame(*trace.origin)
    t0 = trace.estimate[0][0]
    est = np.array(trace.estimate, dtype=float)
    t_est, n_est = (est[:, 0] - t0) / 1e6, est[:, 2]
    meas = np.array([(t, *frame.to_en(lat, lon)) for t, lat, lon in trace.gnss], dtype=float)
    t_meas, n_meas = (meas[:, 0] - t0) / 1e6, meas[:, 2]
    if truth and truth.get("trajectory", {}).get("t_usec"):
        tr = truth["trajectory"]
        t_true = (np.array(tr["t_usec"], dtype=float) - t0) / 1e6
        n_true = np.array([frame.to_en(a, b)[1] for a, b in zip(tr["lat_deg"], tr["lon_deg"])])
        axes[0].plot(t_est, n_est - np.interp(t_est, t_true, n_true), lw=0.8)
        axes[0].set_ylabel("north estimation\nerror (m)")
        axes[1].plot(t_meas, n_meas - np.interp(t_meas, t_true, n_true), lw=0.8, color="tab:orange")
        axes[1].set_ylabel("north measurement\nerror (m)")
    else:
        axes[0].plot(t_est, n_est, lw=0.8, label="estimate")
        axes[0].plot(t_meas, n_meas, lw=0.6, label="GNSS")
        axes[0].legend(loc="best", fontsize=8)
        axes[0].set_ylabel("north (m)")
        axes[1].plot(t_meas, n_meas - np.interp(t_meas, t_est, n_est), lw=0.8, color="tab:orange")
        axes[1].set_ylabel("north GNSS minus\nestimate (m)")
    alarms = report["alarms"]
    key = (alarms[0]["sensor"], alarms[0]["channel"]) if alarms else ("gnss_pos", "north")
    if key not in trace.stats and trace.stats:
        # an alarm without a test of its own (frozen; a gyro named by the heading witnesses): the channel
        # that came closest to its threshold
        key = max(trace.stats, key=lambda k: max(g / h if h > 0 else 0.0 for _, g, h in trace.stats[k]))
    series = np.array(trace.stats.get(key, []), dtype=float)
    if len(series):
        axes[2].plot((series[:, 0] - t0) / 1e6, series[:, 1], lw=0.8, label="statistic")
        axes[2].plot((series[:, 0] - t0) / 1e6, series[:, 2], lw=0.8, ls="--", color="k", label="threshold")
    for a in alarms:
        axes[2].axvline((a["time_usec"] - t0) / 1e6, color="r", lw=1.0 if (a["sensor"], a["channel"]) == key else 0.5)
    for a in (truth or {}).get("attacks", []):
        for ax in axes:
            ax.axvline((a["start_time_usec"] - t0) / 1e6, color="grey", lw=0.8, ls=":")
    # the autopilot's own verdict, where the log holds it: its EKF's test ratios over 1 (shaded) and
    # its GNSS messages (ticks), beside guard's alarms
    shown = set()
    for v in report.get("autopilot", []):
        start = (v["time_usec"] - t0) / 1e6
        label = f"autopilot: {v['source']} {v['test']}" if v.get("end_usec") else "autopilot: GPS message"
        kw = {"label": label} if label not in shown else {}
        shown.add(label)
        if v.get("end_usec"):
            axes[2].axvspan(start, max((v["end_usec"] - t0) / 1e6, start + 0.2), color="tab:purple", alpha=0.2, **kw)
        else:
            axes[2].axvline(start, color="tab:purple", lw=0.8, ls="-.", **kw)
    axes[2].set_ylabel(f"{report['detector']} statistic\n{key[0]} {key[1]}")
    axes[2].set_yscale("symlog")
    axes[2].legend(loc="upper left", fontsize=8)
    axes[2].set_xlabel("time since first fix (s)")
    first = f"first alarm at GNSS sample {alarms[0]['gnss_index']}" if alarms else "no alarm"
    fig.suptitle(f"{report['source'].rsplit('/', 1)[-1]}: {first}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
