"""The replay report (DESIGN.md's contract): a sink that keeps the alarms, clearances and notices,
and the JSON document built from them and from what the reader counted."""

from __future__ import annotations

import json
import sys
from collections import Counter
from dataclasses import asdict
from pathlib import Path

from guard.model.events import Alarm, Cleared, Notice
from guard.model.samples import Attitude, GnssFix, ImuSample
from guard.sinks.base import Sink

KINDS = {GnssFix: "gnss", ImuSample: "imu", Attitude: "attitude"}


class ReportSink(Sink):
    def __init__(self):
        self.alarms: list[dict] = []
        self.cleared: list[dict] = []
        self.notices: list[dict] = []
        self.samples: Counter[str] = Counter()      # samples read, per kind

    def on_sample(self, sample) -> None:
        kind = KINDS.get(type(sample))
        if kind:
            self.samples[kind] += 1

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Alarm):
                self.alarms.append({"time_usec": e.t_us, "gnss_index": e.gnss_index, "sensor": e.sensor,
                                    "channel": e.channel, "statistic": e.statistic, "threshold": e.threshold,
                                    "offset": e.offset, "ambiguous_with": list(e.ambiguous_with)})
            elif isinstance(e, Cleared):
                self.cleared.append({"time_usec": e.t_us, "gnss_index": e.gnss_index, "sensor": e.sensor,
                                     "channel": e.channel})
            elif isinstance(e, Notice):
                self.notices.append({"time_usec": e.t_us, "level": e.level, "text": e.text})

    def report(self, source, monitor, detector_cfg) -> dict:
        """The report of a replay of `source` (a LogSource) through `monitor`."""
        skipped = Counter(source.skipped) + monitor.skipped
        duration = 0.0 if source.first_time_us is None else (source.last_time_us - source.first_time_us) / 1e6
        return {
            "source": str(source.path),
            "format": type(source).__name__.removesuffix("Reader").lower(),
            "duration_s": round(duration, 3),
            "messages": dict(sorted(source.messages.items())),
            "skipped": dict(sorted(skipped.items())),
            "detector": detector_cfg.name,
            "detector_config": json.loads(json.dumps(asdict(detector_cfg))),   # tuples as lists
            "gnss_samples": monitor.gnss_index + 1,
            "samples": dict(sorted(self.samples.items())),
            "rates_hz": {k: round(v, 2) for k, v in getattr(source, "rates_hz", {}).items()},
            "notes": list(source.notes),
            "autopilot": list(source.verdicts),     # the autopilot's own findings, where the log has them
            "peak_ratio": {s: round(v, 3) for s, v in sorted(monitor.detector.peak.items())},
            "alarms": self.alarms,
            "cleared": self.cleared,
            "notices": self.notices,
        }


def write_report(report: dict, out: str) -> None:
    text = json.dumps(report, indent=1) + "\n"
    if out == "-":
        sys.stdout.write(text)
    else:
        Path(out).write_text(text)
