"""The live MAVLink link: a source of samples, and the connection the STATUSTEXT sink sends on
(`guard.sinks.statustext`).

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

from guard.errors import ConfigError, SourceError   # noqa: E402
from guard.sources.mavlink import to_sample                 # noqa: E402

log = logging.getLogger(__name__)

COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER     # 191
WANTED = {"GPS_RAW_INT", "RAW_IMU", "ATTITUDE", "HEARTBEAT"}


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

    def send(self, fn) -> None:
        """Call fn(mav) to send a message; a link without a peer yet or down is counted, not fatal."""
        try:
            fn(self.conn.mav)
        except OSError as e:        # no peer yet (udpin before the first packet), link down
            self.skipped["send_failed"] += 1
            log.debug("send failed: %s", e)

    def close(self) -> None:
        self.conn.close()
