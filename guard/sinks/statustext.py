"""The alarm where the operator looks: STATUSTEXT on the MAVLink link, and guard's own HEARTBEAT and
grd_ratio (NAMED_VALUE_FLOAT) as an onboard computer (component 191).

- STATUSTEXT CRITICAL when an alarm is raised (sensor, axis, estimated offset, GNSS sample), and
  NOTICE when it clears; an alarm stays latched while the sensor is excluded, so it is sent once;
  a sensor whose alarm stands and alarms again (a ramp on a GNSS tested alone, after each
  re-anchoring) is "GUARD still ..." at WARNING, at most once per STANDING_EVERY_S for that sensor
  unless its offset is more than twice the largest said for it (an attack that grew is news);
  a core Notice at WARNING goes out at WARNING. Warnings and notices are rate-limited; an alarm never is.
- A text longer than 50 bytes goes in MAVLink 2 chunks (one id, chunk_seq 0, 1, ...).
- NAMED_VALUE_FLOAT "grd_ratio": the largest statistic/threshold ratio since the last send.
The wording of every line is here; the daemon and the terminal print the same lines.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable

from guard.model.events import UNITS, Alarm, Cleared, Notice
from guard.sinks.base import Sink
from guard.sources.link import MavlinkLink, mavlink

STATUSTEXT_PER_S = 4                                    # rate limit of what we send
STANDING_EVERY_S = 30.0                                 # a standing alarm's repeats: once per this, per sensor,
STANDING_GROWTH = 2.0                                   # or when its offset is this many times the largest said


def alarm_text(e: Alarm, word: str = "ALARM") -> str:
    """At most 50 characters, readable on a ground station: sensor(s), axis, offset, GNSS sample.
    `word` "still": a standing alarm's repeat (the disagreement goes on)."""
    sensors = "|".join((e.sensor, *e.ambiguous_with))     # "mag|gyro": either, the physics cannot tell here
    text = f"GUARD {word} {sensors} {e.channel} {e.offset:+.3g}{UNITS[e.sensor]} k={e.gnss_index}"
    if len(text) > 50:      # "accel|gnss_vel lateral": the unit goes before the GNSS sample's digits do
        text = f"GUARD {word} {sensors} {e.channel} {e.offset:+.3g} k={e.gnss_index}"
    return text[:50]


def clear_text(e: Cleared) -> str:
    return f"GUARD clear {e.sensor} {e.channel} k={e.gnss_index}"


class StatusText(Sink):
    """Sends the core's alarms, clearances and warnings on `link` (None: the terminal only), and
    prints each on `out`. `alarms` counts the core's alarms (a standing one's repeats too, said or
    not); `peak` the largest alarm ratio since the last grd_ratio."""

    def __init__(self, link: MavlinkLink | None, cfg, out: Callable[[str], None], operator: Callable):
        self.link, self.cfg, self.out, self.operator = link, cfg, out, operator
        self.alarms = 0
        self.peak = 0.0
        self.skipped = link.skipped if link is not None else Counter()
        self.t0 = time.monotonic()
        self._next_heartbeat = 0.0
        self._next_stat = 0.0
        self._sent: list[float] = []
        self._owed: list[tuple[str, str]] = []   # texts kept through the rate limit, sent as it allows
        self._text_id = 0                   # the last long STATUSTEXT's chunk id
        self._standing: dict[str, int] = {}     # sensor -> t_us of its last said repeat
        self._said: dict[str, float] = {}       # sensor -> the largest |offset| said of its alarms

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Alarm):
                self.alarms += 1
                self.peak = max(self.peak, e.statistic / e.threshold if e.threshold else 1.0)
                if e.standing:
                    self._again(e)
                    continue
                text = alarm_text(e)
                self._said[e.sensor] = abs(e.offset)        # a new alarm: its repeats are measured from it
                self._standing[e.sensor] = e.t_us
                self.out(f"guard: {text} (t={e.t_us / 1e6:.2f} s, statistic {e.statistic:.1f} > {e.threshold:.1f})")
                self.statustext(text, "critical")
            elif isinstance(e, Cleared):
                self._said.pop(e.sensor, None)
                self._standing.pop(e.sensor, None)
                text = clear_text(e)
                self.out(f"guard: {text}")
                self.statustext(text, "notice")
            elif isinstance(e, Notice):
                self.operator(e.text, level=e.level, send=e.level == "warning")

    def _again(self, e: Alarm) -> None:
        """A standing alarm's repeat: said at WARNING, once per STANDING_EVERY_S per sensor or when its
        offset is STANDING_GROWTH times the largest said; the rest counted. Timed by the samples (a
        replay's too); a time that jumped back (a reboot) says it."""
        last_t = self._standing.get(e.sensor)
        recent = last_t is not None and 0 <= e.t_us - last_t < STANDING_EVERY_S * 1e6
        if recent and abs(e.offset) <= STANDING_GROWTH * self._said.get(e.sensor, 0.0):
            self.skipped["standing_alarm_repeats"] += 1
            return
        text = alarm_text(e, "still")
        sent = self.statustext(text, "warning")     # a rate-limited one is tried again at the next repeat
        self.out(f"guard: {text} (t={e.t_us / 1e6:.2f} s, its alarm stands; statistic {e.statistic:.1f} > "
                 f"{e.threshold:.1f}; said at most every {STANDING_EVERY_S:g} s"
                 f"{'' if sent else '; not sent: rate limit'})")
        if sent:
            self._standing[e.sensor] = e.t_us
            self._said[e.sensor] = max(self._said.get(e.sensor, 0.0), abs(e.offset))

    def tick(self, ratio=lambda: 0.0) -> None:
        """Heartbeat and the statistic (`ratio()`, called only when due), when due; a text kept through
        the rate limit, when it allows."""
        now = time.monotonic()
        while self._owed and self._room(now):
            self.statustext(*self._owed.pop(0))
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 1.0 / self.cfg.heartbeat_hz
            self._send(lambda m: m.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                  0, 0, mavlink.MAV_STATE_ACTIVE))
        if self.cfg.statistic_hz > 0 and now >= self._next_stat:
            self._next_stat = now + 1.0 / self.cfg.statistic_hz
            value = float(ratio())
            ms = int((now - self.t0) * 1000) & 0xFFFFFFFF
            self._send(lambda m: m.named_value_float_send(ms, b"grd_ratio", value))

    def flush(self) -> None:
        """At shutdown: the texts still kept through the rate limit go out now (a line said once is
        not lost with the daemon; they are few)."""
        while self._owed:
            text, level = self._owed.pop(0)
            self._sent.clear()
            self.statustext(text, level)

    def statustext(self, text: str, level: str, keep: bool = False) -> bool:
        """Send a STATUSTEXT at `level` ("critical", "warning" or "notice"). Warnings and notices are
        rate-limited; a CRITICAL alarm never is (it is sent once). Returns whether it went out; `keep`:
        one the limit holds back is sent later (`tick`), not dropped (a line said once)."""
        critical = level == "critical"
        now = time.monotonic()
        if not critical and not self._room(now):
            if keep:
                self._owed.append((text, level))
            else:
                self.skipped["statustext_rate_limited"] += 1
            return False
        self._sent.append(now)
        severity = {"critical": mavlink.MAV_SEVERITY_CRITICAL, "warning": mavlink.MAV_SEVERITY_WARNING}.get(
            level, mavlink.MAV_SEVERITY_NOTICE)
        data = text.encode()
        if len(data) <= 50:
            self._send(lambda m: m.statustext_send(severity, data))
            return True
        # longer: MAVLink 2 chunks (id, chunk_seq), which ground stations join; a chunk shorter than 50
        # bytes ends the text (an empty one if it divides evenly)
        self._text_id = self._text_id % 0xFFFF + 1
        chunks = [data[i:i + 50] for i in range(0, len(data), 50)]
        if len(chunks[-1]) == 50:
            chunks.append(b"")
        for seq, chunk in enumerate(chunks):
            self._send(lambda m: m.statustext_send(severity, chunk, id=self._text_id, chunk_seq=seq))
        return True

    def _room(self, now: float) -> bool:
        """Whether the rate limit lets a warning or a notice out now."""
        self._sent = [t for t in self._sent if now - t < 1.0]
        return len(self._sent) < STATUSTEXT_PER_S

    def _send(self, fn) -> None:
        if self.link is not None:
            self.link.send(fn)
