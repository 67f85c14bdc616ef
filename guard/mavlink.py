"""The MAVLink edge: messages to samples (units converted here, once), and a tlog reader.

GPS_RAW_INT: lat/lon degE7, alt mm, vel cm/s, cog cdeg (UINT16_MAX = unknown), h_acc mm,
vel_acc mm/s; fix_type < 3 is no 3D fix. RAW_IMU (ArduPilot): acceleration mG (specific force),
gyro mrad/s, magnetometer mGauss, body FRD. ATTITUDE: roll, pitch rad; time_boot_ms.
HEARTBEAT of an autopilot (autopilot != INVALID): its type; a GROUND_ROVER is a ground vehicle.

A tlog is a sequence of [8-byte big-endian unix microseconds][MAVLink frame]. The reader splits
frames itself so that garbage between frames, bad CRCs and a truncated tail are counted and
skipped rather than fatal, and it decodes (with pymavlink) only the messages guard uses.
"""

from __future__ import annotations

import datetime
import math
import mmap
import os
from collections import Counter
from collections.abc import Iterator

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink.dialects.v20 import ardupilotmega as mavlink   # noqa: E402

from .errors import SourceError                      # noqa: E402
from .samples import Attitude, GnssFix, ImuSample, Sample, VehicleType   # noqa: E402

G = 9.80665
UNKNOWN_U16 = 65535
WANTED = {mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, mavlink.MAVLINK_MSG_ID_RAW_IMU, mavlink.MAVLINK_MSG_ID_ATTITUDE,
          mavlink.MAVLINK_MSG_ID_HEARTBEAT}
V1, V2 = 0xFE, 0xFD
T_MIN_US, T_MAX_US = 946_684_800_000_000, 4_102_444_800_000_000    # a tlog prefix is unix time: 2000..2100
DAY_US = 86_400_000_000


def to_sample(msg) -> tuple[Sample | None, str | None]:
    """Convert one decoded message to a sample, or (None, reason it was skipped)."""
    name = msg.get_type()
    if name == "GPS_RAW_INT":
        fix_ok = msg.fix_type >= 3
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        if fix_ok and not (abs(lat) <= 90 and abs(lon) <= 180 and (lat, lon) != (0.0, 0.0)):
            return None, "gnss_bad_position"
        vn = ve = None
        if msg.vel != UNKNOWN_U16 and msg.cog != UNKNOWN_U16:
            speed, cog = msg.vel / 100.0, math.radians(msg.cog / 100.0)
            vn, ve = speed * math.cos(cog), speed * math.sin(cog)
        h_acc = getattr(msg, "h_acc", 0)
        vel_acc = getattr(msg, "vel_acc", 0)
        return GnssFix(int(msg.time_usec), fix_ok, lat, lon, msg.alt / 1000.0, vn, ve,
                       h_acc / 1000.0 if h_acc else None, vel_acc / 1000.0 if vel_acc else None), None
    if name == "RAW_IMU":
        a, w = G / 1000.0, 1e-3
        mag = (msg.xmag, msg.ymag, msg.zmag)
        mx, my, mz = (None, None, None) if mag == (0, 0, 0) else (m / 1000.0 for m in mag)
        return ImuSample(int(msg.time_usec), msg.xacc * a, msg.yacc * a, msg.zacc * a,
                         msg.xgyro * w, msg.ygyro * w, msg.zgyro * w, mx, my, mz), None
    if name == "ATTITUDE":
        if not (math.isfinite(msg.roll) and math.isfinite(msg.pitch)) or abs(msg.pitch) > 1.5:
            return None, "attitude_non_finite"
        return Attitude(int(msg.time_boot_ms) * 1000, msg.roll, msg.pitch), None
    if name == "HEARTBEAT":
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:     # a ground station or a companion, not the vehicle
            return None, None
        return VehicleType(msg.type == mavlink.MAV_TYPE_GROUND_ROVER), None
    return None, None


class TlogReader:
    """Iterates over the frames of a tlog; `messages` and `skipped` count what it saw."""

    def __init__(self, path: str, system_id: int = 0):
        self.path = path
        self.system_id = system_id          # 0: any system
        self.messages: Counter[str] = Counter()
        self.skipped: Counter[str] = Counter()
        self.mav = mavlink.MAVLink(None)
        self.mav.robust_parsing = True
        try:
            self._file = open(path, "rb")
        except OSError as e:
            raise SourceError(f"{path}: cannot open: {e.strerror}") from None
        self.size = os.fstat(self._file.fileno()).st_size
        self.position = 0
        first = int.from_bytes(self._file.read(8), "big") if self.size >= 8 else 0
        # the day it was recorded, from the first frame's time prefix (None if the log starts with garbage)
        self.date = (datetime.datetime.fromtimestamp(first / 1e6, datetime.timezone.utc).date()
                     if T_MIN_US <= first <= T_MAX_US else None)
        self.first_time_us: int | None = None
        self.last_time_us: int | None = None

    def close(self) -> None:
        self._file.close()

    def __iter__(self) -> Iterator:
        """Yield decoded messages of the WANTED types (others are only counted)."""
        if self.size == 0:
            return
        with mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            yield from self._frames(buf)

    def _frames(self, buf) -> Iterator:
        size, pos, names = self.size, 0, mavlink.mavlink_map
        decode, count, skip = self.mav.decode, self.messages, self.skipped
        last_t = None
        while pos + 8 < size:
            stx = buf[pos + 8]
            t = int.from_bytes(buf[pos:pos + 8], "big")
            # a frame starts with a start byte after a plausible time prefix; anything else is
            # garbage (or a false start byte inside garbage): resynchronise on the next start byte
            if stx not in (V1, V2) or not (T_MIN_US <= t <= T_MAX_US and (last_t is None or
                                                                       abs(t - last_t) < DAY_US)):
                nxt = min((i for i in (buf.find(b"\xfd", pos + 9), buf.find(b"\xfe", pos + 9)) if i >= 0),
                          default=-1)
                skip["garbage_bytes"] += (nxt - 8 - pos) if nxt >= 0 else size - pos
                if nxt < 0:
                    break
                pos = nxt - 8
                continue
            if stx == V2 and pos + 18 <= size:
                length = 12 + buf[pos + 9] + (13 if buf[pos + 10] & 1 else 0)
                msgid = buf[pos + 15] | buf[pos + 16] << 8 | buf[pos + 17] << 16
                sysid = buf[pos + 13]
            elif stx == V1 and pos + 14 <= size:
                length = 8 + buf[pos + 9]
                msgid, sysid = buf[pos + 13], buf[pos + 11]
            else:
                skip["truncated"] += 1
                break
            end = pos + 8 + length
            if end > size:
                skip["truncated"] += 1
                break
            self.position = end
            kind = names.get(msgid)
            # a frame guard does not use is only counted, not decoded, when it is plausible: a known
            # type and the next frame starting right after it; anything else is checked by its CRC
            plausible = kind is not None and (end == size or end + 8 < size and buf[end + 8] in (V1, V2))
            if msgid not in WANTED and plausible:
                count[kind.msgname] += 1
                last_t = t
                pos = end
                continue
            try:
                msg = decode(bytearray(buf[pos + 8:end]))
            except mavlink.MAVError:
                skip["bad_crc"] += 1
                pos += 1        # perhaps a false start byte: look for the next one
                continue
            last_t = t
            count[msg.get_type()] += 1
            if msgid not in WANTED:
                pos = end
                continue
            if self.system_id and sysid != self.system_id:
                skip["other_system"] += 1
            else:
                self.first_time_us = self.first_time_us or t
                self.last_time_us = t
                yield msg
            pos = end
        else:
            if pos < size:
                skip["truncated"] += 1


def tlog_samples(reader: TlogReader) -> Iterator[Sample]:
    """Samples of a tlog in stream order; conversion failures are counted in reader.skipped."""
    for msg in reader:
        sample, reason = to_sample(msg)
        if sample is not None:
            yield sample
        elif reason:
            reader.skipped[reason] += 1
