"""The live MAVLink link: a source of samples and the way back for alarms.

Any pymavlink connection URL (`udpin:0.0.0.0:14550`, `udpout:127.0.0.1:14550`, `tcp:host:5760`,
`/dev/ttyACM0,57600`). Only the autopilot's system id is read (`link.system_id`, 0 for any); our
own frames (component 191) are ignored. Malformed frames and frames with a bad CRC are counted
in `skipped` and dropped; so are unsigned or wrongly signed frames when signing is required.
"""

from __future__ import annotations

import logging
import os
import time
from collections import Counter, deque

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink import mavutil                                   # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink     # noqa: E402

from .errors import ConfigError, SourceError   # noqa: E402
from .mavlink import to_sample                 # noqa: E402

log = logging.getLogger(__name__)

COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER     # 191
WANTED = {"GPS_RAW_INT", "RAW_IMU", "ATTITUDE", "HEARTBEAT"}
STATUSTEXT_PER_S = 4                                    # rate limit of what we send


def read_key(path: str) -> bytes:
    """A signing key file: 32 raw bytes, or 64 hex digits."""
    try:
        data = open(path, "rb").read()
    except OSError as e:
        raise ConfigError(f"link.signing_key_file: {path}: {e.strerror}") from None
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode())
        except ValueError:
            pass
    if len(data) == 32:
        return data
    raise ConfigError(f"link.signing_key_file: {path}: expected 32 bytes or 64 hex digits")


class MavlinkLink:
    def __init__(self, url: str, cfg):
        self.cfg = cfg
        self.system_id = cfg.system_id
        self.skipped: Counter[str] = Counter()
        try:
            self.conn = mavutil.mavlink_connection(url, source_system=cfg.system_id or 1,
                                                   source_component=COMPONENT_ID, dialect="ardupilotmega",
                                                   autoreconnect=True)
        except Exception as e:    # pymavlink raises many kinds (OSError, SerialException, ValueError)
            raise SourceError(f"cannot open MAVLink link {url}: {e}") from None
        if cfg.signing_key_file:
            allow = None if cfg.require_signed else (lambda mav, msg_id: True)
            self.conn.setup_signing(read_key(cfg.signing_key_file), sign_outgoing=True,
                                    allow_unsigned_callback=allow)
        self.t0 = time.monotonic()
        self._next_heartbeat = 0.0
        self._next_stat = 0.0
        self._sent: list[float] = []
        self._text_id = 0                   # the last long STATUSTEXT's chunk id
        self._pending: deque = deque()

    def poll(self, timeout: float):
        """The next sample from the autopilot, or None after `timeout` seconds without one.

        Reads what the link has and parses it with the link's MAVLink parser (pymavlink's
        recv_match would also copy every message into its per-system state, which we do not use).
        """
        deadline = time.monotonic() + timeout
        while True:
            while self._pending:
                sample = self._take(self._pending.popleft())
                if sample is not None:
                    return sample
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                data = self.conn.recv()
                if not data:
                    self.conn.select(min(remaining, 0.05))
                    continue
                self._pending.extend(self.conn.mav.parse_buffer(data) or ())
            except mavlink.MAVError as e:     # with robust parsing this is rare: a frame it cannot split
                self.skipped["bad_frame"] += 1
                log.debug("receive error: %s", e)
            except OSError as e:
                log.debug("receive error: %s", e)
                time.sleep(min(remaining, 0.05))

    def _take(self, msg):
        """A parsed message to a sample, or None (counted when skipped)."""
        name = msg.get_type()
        if name == "BAD_DATA":
            reason = getattr(msg, "reason", "")
            self.skipped["bad_signature" if "signature" in reason.lower() else "bad_frame"] += 1
            return None
        if msg.get_srcComponent() == COMPONENT_ID and msg.get_srcSystem() == (self.system_id or 1):
            return None         # our own, echoed back
        if self.system_id and msg.get_srcSystem() != self.system_id:
            self.skipped["other_system"] += 1
            return None
        if name not in WANTED:
            return None
        sample, reason = to_sample(msg)
        if reason:
            self.skipped[reason] += 1
        return sample

    def tick(self, ratio=lambda: 0.0) -> None:
        """Heartbeat and the statistic (`ratio()`, called only when due), when due."""
        now = time.monotonic()
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 1.0 / self.cfg.heartbeat_hz
            self._send(lambda m: m.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                  0, 0, mavlink.MAV_STATE_ACTIVE))
        if self.cfg.statistic_hz > 0 and now >= self._next_stat:
            self._next_stat = now + 1.0 / self.cfg.statistic_hz
            value = float(ratio())
            ms = int((now - self.t0) * 1000) & 0xFFFFFFFF
            self._send(lambda m: m.named_value_float_send(ms, b"grd_ratio", value))

    def statustext(self, text: str, level: str) -> None:
        """Send a STATUSTEXT at `level` ("critical", "warning" or "notice"). Warnings and notices are
        rate-limited; a CRITICAL alarm never is (it is sent once)."""
        critical = level == "critical"
        now = time.monotonic()
        self._sent = [t for t in self._sent if now - t < 1.0]
        if not critical and len(self._sent) >= STATUSTEXT_PER_S:
            self.skipped["statustext_rate_limited"] += 1
            return
        self._sent.append(now)
        severity = {"critical": mavlink.MAV_SEVERITY_CRITICAL, "warning": mavlink.MAV_SEVERITY_WARNING}.get(
            level, mavlink.MAV_SEVERITY_NOTICE)
        data = text.encode()
        if len(data) <= 50:
            self._send(lambda m: m.statustext_send(severity, data))
            return
        # longer: MAVLink 2 chunks (id, chunk_seq), which ground stations join; a chunk shorter than 50
        # bytes ends the text (an empty one if it divides evenly)
        self._text_id = self._text_id % 0xFFFF + 1
        chunks = [data[i:i + 50] for i in range(0, len(data), 50)]
        if len(chunks[-1]) == 50:
            chunks.append(b"")
        for seq, chunk in enumerate(chunks):
            self._send(lambda m: m.statustext_send(severity, chunk, id=self._text_id, chunk_seq=seq))

    def _send(self, fn) -> None:
        try:
            fn(self.conn.mav)
        except OSError as e:        # no peer yet (udpin before the first packet), link down
            self.skipped["send_failed"] += 1
            log.debug("send failed: %s", e)

    def close(self) -> None:
        self.conn.close()
