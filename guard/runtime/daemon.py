"""The daemon: `guard run`. Reads a live link, runs the core, alarms on the link, logs to MCAP.

Reads top to bottom: run() -> startup() -> main_loop() -> shutdown(). The signal handlers only set
a flag (a second SIGINT or SIGTERM forces the exit); shutdown finishes the MCAP file, and run()
restores the original handlers on the way out.

What goes out on the link, and its wording, is the STATUSTEXT sink's (`guard.sinks.statustext`).
"""

from __future__ import annotations

import datetime
import logging
import math
import os
import signal
import time
from collections import Counter

from guard.config import Config, dump
from guard.core.monitor import Monitor
from guard.errors import ConfigError, SourceError
from guard.model.samples import GnssFix, ImuSample
from guard.sources.link import MavlinkLink
from guard.sources.live import check_url, open_link
from guard.runtime.agreement import LiveWander
from guard.runtime.deviation import LiveCheck
from guard.runtime.position_wander import LivePositionWander
from guard.runtime.pump import Pump
from guard.runtime.sdnotify import Notifier
from guard.sinks.mcap import UNIX_2001_US, McapLog
from guard.sinks.statustext import StatusText

log = logging.getLogger(__name__)

POLL_S = 0.2            # the loop wakes at least this often (watchdog, heartbeat, link timeout)
LOG_LOST_REPEAT_S = 60.0    # how often to repeat "MCAP log lost" while it stays lost
IMU_HINT = " (RAW_IMU: ArduPilot's SRn_RAW_SENS; HIGHRES_IMU: PX4's onboard mode)"   # what to stream


class WallClock:
    """The MCAP log's UTC (`guard.sinks.mcap`): this computer's clock against the vehicle's time since
    boot, learnt at the first sample and again when they part by more than RESYNC_US (an autopilot
    reboot), not at every sample (the link's jitter would shake the log's timeline)."""

    RESYNC_US = 1_000_000

    def __init__(self):
        self.utc_offset_us: int | None = None

    def saw(self, t_us: int) -> None:
        if t_us >= UNIX_2001_US:            # a time stamp in UTC already (a GNSS's): nothing to learn
            return
        offset = time.time_ns() // 1000 - t_us
        if self.utc_offset_us is None or abs(offset - self.utc_offset_us) > self.RESYNC_US:
            self.utc_offset_us = offset


class Fanout:
    """The links guard's own messages go out on: the one it reads (its peer) and link.gcs."""

    def __init__(self, links):
        self.links = [link for link in links if link is not None]
        # what the sink counts (rate-limited texts) goes with the main link's counts
        self.skipped = self.links[0].skipped if self.links else Counter()

    def send(self, fn) -> None:
        for link in self.links:
            link.send(fn)


def writable(path: str) -> None:
    """An MCAP target guard can write (a directory, created if missing, or a file's directory), or a
    ConfigError naming it, before the link opens: not "logging to" and then nothing logged."""
    directory = path if not path.endswith(".mcap") else os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"log.mcap: {path}: cannot create {directory}: {e.strerror}") from None
    if not os.path.isdir(directory) or not os.access(directory, os.W_OK | os.X_OK):
        raise ConfigError(f"log.mcap: {path}: {directory} is not a directory this user can write "
                          f"(run as the user the service runs as, or give it the directory)")


def say(line: str) -> None:
    """An operator line on stdout, flushed at once (a pipe or the journal would hold it back)."""
    print(line, flush=True)


class Daemon:
    def __init__(self, cfg: Config, *, connect: str | None = None, mcap: str | None = None, out=say):
        self.cfg = cfg
        self.connect = connect or cfg.link.connect
        self.mcap_path = cfg.log.mcap if mcap is None else mcap
        self.out = out                      # where operator lines go (the terminal)
        # the core never reads the clock: the daemon tells it the day (the magnetic declination's)
        self.monitor = Monitor(cfg.monitor, record_tests=bool(self.mcap_path), date=datetime.date.today())
        self.pump = Pump(self.monitor)
        self.started = False
        self._log_errors = 0
        self._log_warned = -math.inf
        self.notifier = Notifier()
        self.should_exit = False
        self.source = None
        self.link: MavlinkLink | None = None
        self.gcs: MavlinkLink | None = None         # link.gcs: where guard's messages go as well
        self._output_only: list[MavlinkLink] = []   # links guard sends on but takes no samples from
        self.log: McapLog | None = None
        self.status = StatusText(None, cfg.link, out, self._core_notice)
        self.clock = WallClock()
        self._handlers = {}

    # -- life cycle ---------------------------------------------------------------------------------
    def run(self) -> int:
        """The command: serve() with SIGINT and SIGTERM handled."""
        self.install_signal_handlers()
        try:
            return self.serve()
        finally:
            self.restore_signal_handlers()

    def serve(self) -> int:
        """Until should_exit is set (by a signal, or by the caller from another thread)."""
        try:
            self.startup()
            self.main_loop()
        finally:
            self.shutdown()
        return 0

    def startup(self) -> None:
        link_cfg = self.cfg.link
        if self.mcap_path:
            writable(self.mcap_path)
        self.source = open_link(self.connect, self.cfg)
        if isinstance(self.source, MavlinkLink):
            self.link = self.source
        elif link_cfg.connect and not link_cfg.connect.startswith("can:"):
            check_url(link_cfg.connect)
            self.link = MavlinkLink(link_cfg.connect, link_cfg)     # alarms still go out on MAVLink
        if link_cfg.gcs:            # a ground station the router in between does not forward guard's messages to
            if check_url(link_cfg.gcs) == "can":
                raise ConfigError(f"link.gcs: {link_cfg.gcs}: expected a MAVLink URL such as udpout:HOST:PORT")
            self.gcs = MavlinkLink(link_cfg.gcs, link_cfg)
        if self.mcap_path:
            c = self.cfg.log
            self.log = McapLog(self.mcap_path, rotate_mb=c.rotate_mb or None, rotate_s=c.rotate_s or None,
                               keep_mb=c.keep_mb or None,
                               chunk_size=int(c.chunk_kb * 1024),
                               metadata={"config": self.cfg.source_text, "config_in_effect": dump(self.cfg),
                                         "connect": self.connect}, clock=self.clock)
            self.pump.sinks.append(self.log)
        self.status = StatusText(Fanout([self.link, self.gcs]), link_cfg, self.out, self._core_notice)
        self._output_only = [k for k in (self.link, self.gcs) if k is not None and k is not self.source]
        self.pump.sinks.append(self.status)
        # a compass that reads off by heading: said once
        self.pump.sinks.append(LiveCheck(lambda line: self._operator(line, keep=True), self.cfg.monitor))
        # levelled accelerometers that wander from the GNSS: said once (guard.runtime.agreement)
        self.pump.sinks.append(LiveWander(lambda line: self._operator(line, keep=True)))
        # a receiver whose position wanders from its own velocity past the model: said once
        # (guard.runtime.position_wander)
        self.pump.sinks.append(LivePositionWander(lambda line: self._operator(line, keep=True),
                                                  self.cfg.monitor.filter))
        self.out(f"guard: listening on {self.connect}" + (f", logging to {self.mcap_path}" if self.log else ""))
        self.started = True
        self.notifier.ready(f"listening on {self.connect}")

    def main_loop(self) -> None:
        # the time each stream last sent a sample (a HEARTBEAT or an ATTITUDE alone is not data), and
        # which streams were last reported silent: an autopilot that streams GNSS but not the IMU
        # (ArduPilot sends RAW_IMU only when its SRn_RAW_SENS rate is set; PX4 sends HIGHRES_IMU on a link in
        # its onboard mode, none on a telemetry link) is told so, and where each comes from
        last = dict.fromkeys(("GNSS", "IMU"), time.monotonic())
        silent: set[str] = set()
        timeout = self.cfg.link.link_timeout_s
        while not self.should_exit:
            self.notifier.watchdog()
            self.status.tick(self.ratio)
            sample = self.source.poll(POLL_S)
            for link in self._output_only:      # heard too, or a udpin one would never learn whom to answer
                link.drain()
            now = time.monotonic()
            if isinstance(sample, GnssFix):
                last["GNSS"] = now
            elif isinstance(sample, ImuSample):
                last["IMU"] = now
            quiet = {k for k, t in last.items() if now - t > timeout}
            if quiet != silent:
                if not quiet:
                    self._operator("data is back", level="info")
                elif quiet - silent:                # a stream fell silent
                    what = "GNSS or IMU" if len(quiet) == 2 else next(iter(quiet))
                    hint = IMU_HINT if quiet == {"IMU"} else ""
                    self._operator(f"no {what} data for {timeout:g} s: waiting{hint}{self._other_systems()}")
                else:                               # one came back, the other is still silent
                    self._operator(f"{next(iter(silent - quiet))} data is back, still no "
                                   f"{next(iter(quiet))} data", level="info")
                silent = quiet
            if sample is not None:
                self.handle(sample)

    def handle(self, sample) -> list:
        """One sample through the core and out to the sinks."""
        if self.log is not None and isinstance(sample, (GnssFix, ImuSample)):
            self.clock.saw(sample.t_us)
        events = self.pump.feed(sample)
        if self.log is not None and self.log.errors > self._log_errors:    # the sink logged why; tell the operator too
            self._log_errors = self.log.errors
            if time.monotonic() - self._log_warned >= LOG_LOST_REPEAT_S:
                self._log_warned = time.monotonic()
                self._operator("MCAP log lost: still detecting")
        return events

    @property
    def samples(self) -> int:
        return self.pump.samples

    @property
    def alarms(self) -> int:
        return self.status.alarms

    def ratio(self) -> float:
        """grd_ratio: the largest statistic/threshold since the last call (an alarm's included), at least
        1.0 while a sensor is excluded."""
        peak, self.status.peak = self.status.peak, 0.0
        latched = 1.0 if self.monitor.alarmed else 0.0
        return max(peak, latched, self.monitor.detector.take_peak())

    def _core_notice(self, text: str, level: str = "warning", send: bool = True) -> None:
        """A Notice of the core's: the MCAP log has it already (as an event)."""
        self._operator(text, level, send, logged=True)

    def _other_systems(self) -> str:
        """Where the link heard fixes from systems it does not read (an autopilot whose SYSID_THISMAV is not
        link.system_id): which, and what to set; else nothing."""
        heard = getattr(self.source, "other_gnss", None)
        if not heard:
            return ""
        ids = sorted(heard)
        who = f"system {ids[0]} sends" if len(ids) == 1 else f"systems {', '.join(map(str, ids))} send"
        return f" ({who} GPS_RAW_INT, guard reads system {self.cfg.link.system_id}: --system-id or link.system_id)"

    def _operator(self, text: str, level: str = "warning", send: bool = True, logged: bool = False,
                  keep: bool = False) -> None:
        """`keep`: a line said once, sent when the STATUSTEXT rate limit allows rather than dropped."""
        (log.warning if level == "warning" else log.info)("%s", text)
        if self.log is not None and not logged:     # the log holds what the operator was told
            self.log.note(self.monitor.t_us or 0, level, text)
        if send:
            self.status.statustext(f"GUARD {text}", level, keep)

    def summary(self) -> str:
        skipped = Counter(self.monitor.skipped)
        for part in {id(p): p for p in (self.source, self.link, self.gcs) if p is not None}.values():
            skipped.update(getattr(part, "skipped", None) or getattr(part, "stats", None) or {})
        skipped = {k: v for k, v in sorted(skipped.items()) if v}
        lost = f", MCAP errors {self.log.errors} ({self.log.lost_messages} messages lost)" if self.log and \
            self.log.errors else ""
        adjusted = dict(sorted(self.monitor.adjusted.items()))
        used = f"; used adjusted {adjusted}" if adjusted else ""
        return f"guard: stopped after {self.samples} samples, {self.alarms} alarm(s); skipped {skipped}{used}{lost}"

    def shutdown(self) -> None:
        if self.started:
            self.notifier.stopping()
        self.pump.finish()          # what the core still owed (an alarm's estimate) reaches the log
        self.status.flush()         # a line kept through the rate limit is not lost with the daemon
        if self.log is not None:
            self.log.close()
            if self.log.errors:
                log.error("MCAP log: %d write errors, %d messages lost", self.log.errors, self.log.lost_messages)
        for part in {id(p): p for p in (self.source, self.link, self.gcs) if p is not None}.values():
            try:
                part.close()
            except (OSError, SourceError) as e:
                log.warning("closing %s: %s", type(part).__name__, e)
        if self.started:
            self.out(self.summary())

    # -- signals --------------------------------------------------------------------------------------
    def install_signal_handlers(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._handlers[sig] = signal.signal(sig, self.handle_exit)

    def restore_signal_handlers(self) -> None:
        for sig, handler in self._handlers.items():
            signal.signal(sig, handler)
        self._handlers.clear()

    def handle_exit(self, sig, frame) -> None:
        if self.should_exit:
            raise KeyboardInterrupt     # a second signal: stop now, shutdown() still runs
        self.should_exit = True
