"""Offline replay of a tlog through the core: the report of DESIGN.md, and what a plot needs."""

from __future__ import annotations

import json
import sys
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path

from .config import Config
from .core import Monitor
from .events import Alarm, Cleared, Estimate, Notice, Tested
from .mavlink import TlogReader, tlog_samples
from .samples import GnssFix


class Trace:
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


class Progress:
    """A progress bar on stderr, only when stderr is a terminal."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.enabled, self.last = max(total, 1), enabled and sys.stderr.isatty(), 0.0

    def update(self, done: int, force: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (now - self.last < 0.2 and not force):
            return
        self.last = now
        frac = min(1.0, done / self.total)
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\rreplay [{bar:<30}] {100 * frac:5.1f} %")
        if force:
            sys.stderr.write("\n")
        sys.stderr.flush()


def replay(path: str, cfg: Config | None = None, *, listeners=(), progress: bool = False) -> dict:
    """Run a tlog through the core; return the report (JSON-ready dict).

    `listeners` get on_sample(sample) and on_events(events) for every sample (a Trace, an McapLog).
    """
    cfg = cfg or Config()
    reader = TlogReader(path, cfg.link.system_id if cfg.link.system_id else 0)
    monitor = Monitor(cfg.monitor, record_tests=bool(listeners), date=reader.date)
    bar = Progress(reader.size, progress)
    alarms, cleared, notices = [], [], []
    try:
        for i, sample in enumerate(tlog_samples(reader)):
            events = monitor.step(sample)
            for sink in listeners:
                sink.on_sample(sample)
                sink.on_events(events)
            for e in events:
                if isinstance(e, Alarm):
                    alarms.append({"time_usec": e.t_us, "gnss_index": e.gnss_index, "sensor": e.sensor,
                                   "channel": e.channel, "statistic": e.statistic, "threshold": e.threshold,
                                   "offset": e.offset, "ambiguous_with": list(e.ambiguous_with)})
                elif isinstance(e, Cleared):
                    cleared.append({"time_usec": e.t_us, "gnss_index": e.gnss_index, "sensor": e.sensor,
                                    "channel": e.channel})
                elif isinstance(e, Notice):
                    notices.append({"time_usec": e.t_us, "level": e.level, "text": e.text})
            if i % 2048 == 0:
                bar.update(reader.position)
        owed = monitor.finish()                 # what the last sample still owed (an alarm's Estimate)
        for sink in listeners:
            sink.on_events(owed)
        bar.update(reader.size, force=True)
    finally:
        reader.close()
    skipped = Counter(reader.skipped) + monitor.skipped
    duration = 0.0 if reader.first_time_us is None else (reader.last_time_us - reader.first_time_us) / 1e6
    return {
        "source": str(path),
        "duration_s": round(duration, 3),
        "messages": dict(sorted(reader.messages.items())),
        "skipped": dict(sorted(skipped.items())),
        "detector": cfg.monitor.detector.name,
        "detector_config": json.loads(json.dumps(asdict(cfg.monitor.detector))),   # tuples as lists
        "gnss_samples": monitor.gnss_index + 1,
        "peak_ratio": {s: round(v, 3) for s, v in sorted(getattr(monitor.detector, "peak", {}).items())},
        "alarms": alarms,
        "cleared": cleared,
        "notices": notices,
    }


def write_report(report: dict, out: str) -> None:
    text = json.dumps(report, indent=1) + "\n"
    if out == "-":
        sys.stdout.write(text)
    else:
        Path(out).write_text(text)


def truth_beside(path: str) -> dict | None:
    """The simulator's NAME.truth.json beside NAME.tlog, if there is one."""
    p = Path(path)
    truth = p.with_name(p.name.removesuffix(".tlog") + ".truth.json")
    if not truth.is_file():
        return None
    try:
        return json.loads(truth.read_text())
    except (OSError, ValueError):
        return None
