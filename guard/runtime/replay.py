"""Offline replay of a log through the core: the report of DESIGN.md, and what a figure needs.

The log's format is recognised by its content (`guard.sources.open_log`); its samples go through the
same pump as the daemon's.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from guard.config import Config
from guard.core.monitor import Monitor
from guard.errors import SourceError
from guard.runtime.pump import Pump
from guard.sinks.report import ReportSink, write_report
from guard.sources import open_log

__all__ = ["Progress", "replay", "truth_beside", "write_report"]


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


def replay(path: str, cfg: Config | None = None, *, listeners=(), progress: bool = False,
           imu: int | None = None, gnss: int | None = None, inject=None) -> dict:
    """Run a log through the core; return the report (JSON-ready dict).

    `listeners` are sinks: they get on_sample(sample) and on_events(events) for every sample (a
    Trace, an McapLog). `imu`, `gnss`: which instance, in a log that holds several (None: the
    primary). `inject`: a function of the log's sample stream that returns the stream the core is
    to see (an attack written into a real flight, tools/real_logs.py --attack). A log from which no
    GNSS fix could be read, or only messages without a 3D fix, is a SourceError saying what was found:
    never a clean-looking report of nothing.
    """
    cfg = cfg or Config()
    options = {k: v for k, v in (("imu", imu), ("gnss", gnss)) if v is not None}
    source = open_log(path, system_id=cfg.link.system_id if cfg.link.system_id else 0, **options)
    monitor = Monitor(cfg.monitor, record_tests=any(getattr(sink, "needs_tests", True) for sink in listeners),
                      date=source.date)
    for sink in listeners:
        if getattr(sink, "clock", False) is None:      # a sink that logs in UTC where the log says it
            sink.clock = source
    report = ReportSink()
    pump = Pump(monitor, [report, *listeners])
    bar = Progress(source.size, progress)
    try:
        samples = source.samples()
        pump.run(inject(samples) if inject else samples, every=2048, tick=lambda: bar.update(source.position))
        bar.update(source.size, force=True)
    finally:
        source.close()
    out = report.report(source, monitor, cfg.monitor.detector)
    if not out["samples"].get("gnss"):
        raise SourceError(f"{path}: no GNSS sample could be read: {nothing_read(out)}")
    if out["samples"]["gnss"] == out["skipped"].get("gnss_no_fix", 0):     # a bench test, a flight indoors
        raise SourceError(f"{path}: no GNSS message with a 3D fix, nothing to monitor: {nothing_read(out)}")
    if out["samples"]["gnss"] == sum(out["skipped"].get(k, 0) for k in ("gnss_no_fix", "gnss_coarse_before_start")):
        raise SourceError(f"{path}: no GNSS fix good enough to start on (5 m, or HDOP 5), nothing monitored: "
                          f"{nothing_read(out)}")
    return out


def nothing_read(report: dict) -> str:
    """What a log held, in one line, when it held nothing guard could monitor."""
    found = ", ".join(f"{n} {k}" for k, n in sorted(report["messages"].items(), key=lambda kv: -kv[1])[:6])
    skipped = ", ".join(f"{n} {k}" for k, n in sorted(report["skipped"].items(), key=lambda kv: -kv[1])[:4])
    return f"found {found or 'no message'}" + (f"; skipped {skipped}" if skipped else "")


def truth_beside(path: str) -> dict | None:
    """The simulator's NAME.truth.json beside NAME.tlog (.bin, .ulg), if there is one."""
    p = Path(path)
    truth = p.with_name(p.stem + ".truth.json")
    if not truth.is_file():
        return None
    try:
        return json.loads(truth.read_text())
    except (OSError, ValueError):
        return None
