"""The live MAVLink link: a source of samples, and the connection the STATUSTEXT sink sends on
(`guard.sinks.statustext`).

Any pymavlink connection URL (`udpin:0.0.0.0:14550`, `udpout:127.0.0.1:14550`, `udpbcast:`, `tcp:host:5760`,
`/dev/ttyACM0,57600`). Only the autopilot's system id is read (`link.system_id`, 0 for any); our
own frames (component 191) are ignored. The link may be hostile; what it does about that:

- **Framing** (`guard.sources.framing`). pymavlink opens the connection, packs what we send and decodes
  fields; finding frames is ours. On UDP each datagram is parsed on its own: a frame cut off at the
  end of a datagram is dropped (`skipped["partial_frame"]`), never joined with the next datagram, so
  fragments from two senders cannot make a frame. A failed frame start (a stray 0xFD, a bad CRC)
  is skipped by one byte, not by the length it claims, so it costs no valid frame after it. TCP
  and serial are a stream: an incomplete frame is kept (under 280 bytes) until the next read.
- **Signing before state.** With a key, a frame's signature and time stamp are checked
  (`framing.verify`) before pymavlink sees it: pymavlink records a stream's time stamp before it
  checks the signature, so one forged frame stamped 2^48 - 2 would make it drop every genuine one.
  A wrongly signed or replayed frame is dropped even when unsigned ones are allowed.
- **One peer.** pymavlink's udpin remembers every source address and sends to all of them. Here we
  read the UDP socket ourselves and keep one address: the peer, the sender of the first valid
  frame (CRC, signature, system id) from the autopilot. Frames from other addresses are dropped
  (`skipped["other_address"]`) until the peer has been silent for `link.link_timeout_s`; then the
  next valid autopilot frame names the new peer (an autopilot that restarted on a new port). What
  we send goes to the peer only (udpin: nothing until one is heard, `skipped["send_no_peer"]`;
  udpbcast: the broadcast address until then; udpout: always the address in the URL).
- **Counted, logged sparingly.** Every dropped frame is counted in `skipped` by reason; a reason
  is logged at most once per LOG_EVERY_S, with the count since its last line.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import socket
import time
from collections import Counter, deque

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink import mavutil                                   # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink     # noqa: E402

from guard.errors import ConfigError, SourceError   # noqa: E402
from guard.model.samples import GnssFix, ImuSample   # noqa: E402
from guard.sources import framing                   # noqa: E402
from guard.sources.mavlink import IMU_MESSAGES, CompassRepeats, ImuStream, UnixFixes, to_sample   # noqa: E402
from guard.sources.rates import StreamRates         # noqa: E402

log = logging.getLogger(__name__)

COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER     # 191
WANTED = {"GPS_RAW_INT", "RAW_IMU", "HIGHRES_IMU", "ATTITUDE", "HEARTBEAT"}
RCVBUF_BYTES = 4 << 20          # a UDP link's receive buffer, asked for (see MavlinkLink)
LOG_EVERY_S = 10.0              # at most one log line per skip reason this often
UDP_MAX = 65535
WARN_REASONS = {"bad_signature", "other_address"}     # signs of an attack: WARNING, the rest INFO


def read_key(path: str) -> bytes:
    """A signing key file: 32 raw bytes, or 64 hex digits."""
    try:
        with open(path, "rb") as f:
            data = f.read()
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


class SkipLog:
    """Counts skips by reason into `skipped`, and logs a reason at most once per `every_s`: the
    first at once, then the count since the last line."""

    def __init__(self, skipped: Counter, every_s: float = LOG_EVERY_S, clock=time.monotonic):
        self.skipped, self.every_s, self.clock = skipped, every_s, clock
        self._unlogged: Counter[str] = Counter()
        self._last: dict[str, float] = {}           # one entry per reason: a fixed set
        self._detail: dict[str, str] = {}

    def __call__(self, reason: str, n: int = 1, detail: str = "") -> None:
        self.skipped[reason] += n
        self._unlogged[reason] += n
        if detail:
            self._detail[reason] = detail
        now = self.clock()
        if now - self._last.get(reason, -math.inf) >= self.every_s:
            self._emit(reason, now)

    def flush(self) -> None:
        """Log what was counted since each reason's last line."""
        now = self.clock()
        for reason in [r for r, n in self._unlogged.items() if n]:
            self._emit(reason, now)

    def _emit(self, reason: str, now: float) -> None:
        n = self._unlogged.pop(reason)
        since = now - self._last[reason] if reason in self._last else None
        self._last[reason] = now
        detail = self._detail.pop(reason, "")
        level = logging.WARNING if reason in WARN_REASONS else logging.INFO
        log.log(level, "MAVLink link: skipped %d %s%s%s", n, reason,
                f" in the last {since:.0f} s" if since is not None else "", f" (last: {detail})" if detail else "")


class _NoPeer(OSError):
    pass


class _UdpOut:
    """pymavlink's `file` for what we send on a UDP link: each frame one datagram, to `to` alone."""

    def __init__(self, sock: socket.socket, to=None):
        self.sock, self.to = sock, to

    def write(self, buf) -> None:
        if self.to is None:
            raise _NoPeer("no peer heard yet")
        self.sock.sendto(buf, self.to)


def refuse_taken_port(url: str) -> None:
    """A SourceError when a udpin port is bound already (another guard, a router on the same port).
    pymavlink binds with SO_REUSEADDR, with which Linux lets a second program bind the same UDP port
    and take its traffic silently; a plain bind, tried and released first, cannot."""
    scheme, _, rest = url.partition(":")
    host, _, port = rest.rpartition(":")
    if scheme != "udpin" or not port.isdigit() or int(port) == 0:
        return
    probe = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host or "0.0.0.0", int(port)))
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise SourceError(f"cannot open MAVLink link {url}: UDP port {port} is in use by another program "
                              "(another guard, or a router listening on it); stop it or pick another port") from None
    finally:
        probe.close()


class MavlinkLink:
    def __init__(self, url: str, cfg, min_imu_hz: float | None = None):
        """`min_imu_hz` (the monitor's): the link guard reads its data from, whose streams it asks the
        autopilot for (link.request_rates); None: a link guard only sends on, which asks for nothing."""
        self.cfg = cfg
        self.system_id = cfg.system_id
        self.skipped: Counter[str] = Counter()
        self.skip = SkipLog(self.skipped)
        self.other_gnss: Counter[int] = Counter()   # systems not read that send GPS_RAW_INT: the daemon names
                                                    # them when the data it reads falls silent
        self.repeats = CompassRepeats()             # a slower compass's reading, once
        self.unix_fixes = UnixFixes(log.warning)    # fixes stamped in UNIX time, on the boot clock
        self.imu_stream = ImuStream(log.warning)    # RAW_IMU (ArduPilot) or HIGHRES_IMU (PX4), not both
        # the streams guard reads, asked of the autopilot at rates it can use (guard.sources.rates)
        self.rates = StreamRates(log.warning, min_imu_hz, lambda: self.imu_stream.kind, log.info) \
            if cfg.request_rates and min_imu_hz is not None else None
        refuse_taken_port(url)
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
        self.udp = isinstance(self.conn, mavutil.mavudp)
        self.datagrams = self.udp or isinstance(self.conn, mavutil.mavmcast)
        self.peer = None                    # UDP: the autopilot's address, once heard
        self._peer_heard = -math.inf
        self._out = None
        self._follow_peer = False           # udpin and udpbcast answer the peer; udpout its own address
        if self.udp:
            # a burst of junk must not push the autopilot's frames out of the kernel's queue: ask for a
            # larger receive buffer (the kernel caps it at net.core.rmem_max; what it still drops, it
            # counts in /proc/net/snmp, Udp RcvbufErrors)
            with contextlib.suppress(OSError):
                self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
            self._follow_peer = self.conn.udp_server or self.conn.broadcast
            self._out = _UdpOut(self.conn.port, self._first_destination(url))
            self.conn.mav.file = self._out      # pymavlink's write would send to every address seen
        self._tail = b""                    # a stream's incomplete frame
        self._pending: deque = deque()
        self._draining = False              # drain(): other systems are expected (a ground station)

    def _first_destination(self, url: str):
        """Where a UDP link sends before a peer is heard: udpout's and udpbcast's address, udpin's none."""
        if self.conn.udp_server:
            return None
        host, port = self.conn.destination_addr
        try:
            return socket.gethostbyname(host), port
        except OSError as e:
            raise SourceError(f"cannot open MAVLink link {url}: {e}") from None

    def poll(self, timeout: float):
        """The next sample from the autopilot, or None after `timeout` seconds without one."""
        deadline = time.monotonic() + timeout
        if self.rates is not None:
            for request in self.rates.due(time.monotonic()):
                self.send(request)
        while True:
            while self._pending:
                sample = self._take(self._pending.popleft())
                if sample is not None:
                    return sample
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                if not self._read():
                    self.conn.select(min(remaining, 0.05))
            except OSError as e:
                log.debug("receive error: %s", e)
                time.sleep(min(remaining, 0.05))

    def drain(self, most: int = 256) -> int:
        """Read what is waiting (at most `most` reads), without blocking, and drop its samples: a link
        that carries only guard's own messages (the alarms of a monitor reading CAN, `link.gcs`) still
        hears its peer, the one it answers, and its socket does not fill. Frames of other systems (the
        ground station's own) are not counted as skipped there. Returns the reads made."""
        n = 0
        self._draining = True
        try:
            while n < most and self._read():
                n += 1
        except OSError as e:
            log.debug("receive error: %s", e)
        finally:
            self._draining = False
        self._pending.clear()
        return n

    def _read(self) -> bool:
        """Read one datagram (UDP) or what the stream has, and queue its accepted messages; False when
        there was nothing to read."""
        addr = None
        if self.udp:
            try:
                data, addr = self.conn.port.recvfrom(UDP_MAX)
            except (BlockingIOError, InterruptedError, ConnectionRefusedError):    # refused: udpout's ICMP
                return False
        else:
            data = self.conn.recv()
            if not data:
                return False
        if self.datagrams:
            found = framing.split(data, final=True)
        else:
            data = self._tail + data
            found = framing.split(data, final=False)
            self._tail = data[found.rest:]
        if found.bad:
            self.skip("bad_frame", found.bad)
        if found.partial:
            self.skip("partial_frame", found.partial)
        for frame in found.frames:
            msg = self._accept(frame, addr)
            if msg is not None:
                self._pending.append(msg)
        return True

    def _accept(self, frame: framing.Frame, addr):
        """The decoded message of a CRC-checked frame from `addr` (None: a stream), or None (counted).

        Signature first: nothing of pymavlink's state changes for a frame that fails it."""
        why = framing.verify(frame, self.conn.mav.signing, self.cfg.require_signed)
        if why is not None:
            self.skip("bad_signature", detail=why)
            return None
        if frame.component == COMPONENT_ID and frame.system == (self.system_id or 1):
            return None         # our own, echoed back
        if self.system_id and frame.system != self.system_id:
            if self._draining:      # a link guard only sends on: a ground station's frames are no skipped
                if addr is not None:                # sample, and a udpin one answers the first it heard
                    self._from_peer(addr)
            elif frame.msg_id != mavlink.MAVLINK_MSG_ID_HEARTBEAT:     # a heartbeat is no data (a ground
                self.skip("other_system")                              # station's, routed here): not counted
                if frame.msg_id == mavlink.MAVLINK_MSG_ID_GPS_RAW_INT:
                    self.other_gnss[frame.system] += 1
            return None
        try:
            msg = self.conn.mav.decode(bytearray(frame.buf))     # records the signed stream's time stamp
        except mavlink.MAVError as e:
            self.skip("bad_signature" if "signature" in e.message.lower() else "bad_frame", detail=e.message)
            return None
        if addr is not None and not self._from_peer(addr):
            self.skip("other_address", detail=f"{addr[0]}:{addr[1]}")
            return None
        return msg

    def _from_peer(self, addr) -> bool:
        """Whether a valid autopilot frame from `addr` is the peer's (which it names when there is none
        or the peer has been silent for link_timeout_s)."""
        now = time.monotonic()
        if addr != self.peer:
            silent_s = now - self._peer_heard
            if self.peer is not None and silent_s <= self.cfg.link_timeout_s:
                return False
            who = "guard's peer" if self._draining else "the autopilot"    # drained: whoever talks to it
            if self.peer is None:
                log.info("MAVLink link: %s is at %s:%d", who, *addr)
            else:
                log.warning("MAVLink link: %s moved from %s:%d to %s:%d (silent for %.0f s)",
                            who, *self.peer, *addr, silent_s)
            self.peer = addr
            if self._follow_peer:
                self._out.to = addr
        self._peer_heard = now
        return True

    def _take(self, msg):
        """A decoded message to a sample, or None (counted when skipped)."""
        if self.rates is not None:
            self.rates.heard(msg, time.monotonic())
        if (kind := msg.get_type()) not in WANTED:
            return None
        if kind in IMU_MESSAGES and not self.imu_stream(kind):
            self.skip("imu_other_stream")
            return None
        sample, reason = to_sample(msg)
        if reason:
            self.skip(reason)
        arrival = int(time.monotonic() * 1e6)
        if isinstance(sample, ImuSample):
            self.unix_fixes.imu(sample.t_us, arrival)
            return self.repeats(sample)
        if isinstance(sample, GnssFix):
            return self.unix_fixes.fix(sample, arrival)
        return sample

    def send(self, fn) -> None:
        """Call fn(mav) to send a message; a link without a peer yet or down is counted, not fatal."""
        try:
            fn(self.conn.mav)
        except _NoPeer:             # udpin before the autopilot is heard
            self.skip("send_no_peer", detail="no autopilot heard yet")
        except OSError as e:        # link down, or refused
            self.skip("send_failed", detail=str(e))

    def close(self) -> None:
        self.skip.flush()
        self.conn.close()
