"""tlog files: [8-byte big-endian unix microseconds][MAVLink frame], as MAVProxy and Mission Planner
write them. The reader splits frames itself so that garbage between frames, bad CRCs and a truncated
tail are counted and skipped rather than fatal, and it decodes (with pymavlink) only the messages
guard uses; `guard.sources.mavlink.to_sample` converts them (units, once).
"""

from __future__ import annotations

import dataclasses
import datetime
import mmap
import os
from collections import Counter
from collections.abc import Iterator

from guard.errors import SourceError
from guard.model.samples import GnssFix, ImuSample, Sample
from guard.sources.base import LogSource
from guard.sources.clock import epoch_clock, motion_clock
from guard.sources.mavlink import IMU_MESSAGES, WANTED, CompassRepeats, ImuStream, UnixFixes, mavlink, to_sample

V1, V2 = 0xFE, 0xFD
T_MIN_US, T_MAX_US = 946_684_800_000_000, 4_102_444_800_000_000    # a tlog prefix is unix time: 2000..2100
DAY_US = 86_400_000_000
GNSS_ONLY = {mavlink.MAVLINK_MSG_ID_GPS_RAW_INT}


def looks_like_tlog(head: bytes) -> bool:
    """A tlog starts with a plausible unix-microsecond prefix and a MAVLink start byte."""
    return len(head) >= 9 and T_MIN_US <= int.from_bytes(head[:8], "big") <= T_MAX_US and head[8] in (V1, V2)


class TlogReader(LogSource):
    """Iterates over the frames of a tlog; `messages` and `skipped` count what it saw."""

    PEEK_SAMPLES = 5000     # how far into the log opening looks for the first IMU sample's time

    def __init__(self, path: str, system_id: int = 0, peek: bool = True):
        super().__init__()
        self.path = path
        self.system_id = system_id          # 0: any system
        self.mav = mavlink.MAVLink(None)
        self.mav.robust_parsing = True
        try:
            self._file = open(path, "rb")
        except OSError as e:
            raise SourceError(f"{path}: cannot open: {e.strerror}") from None
        try:
            self.size = os.fstat(self._file.fileno()).st_size
            first = int.from_bytes(self._file.read(8), "big") if self.size >= 8 else 0
        except OSError as e:
            self._file.close()
            raise SourceError(f"{path}: cannot read: {e.strerror}") from None
        self.position = 0
        # the day it was recorded, from the first frame's time prefix (None if the log starts with garbage)
        self.date = (datetime.datetime.fromtimestamp(first / 1e6, datetime.timezone.utc).date()
                     if T_MIN_US <= first <= T_MAX_US else None)
        self.first_time_us: int | None = None
        self.last_time_us: int | None = None
        if peek:
            try:
                self._peek(path, system_id)
            except BaseException:
                self._file.close()
                raise

    def _peek(self, path: str, system_id: int) -> None:
        """UTC from the start (a no-fix GNSS message has no time to learn it from), and the clock."""
        if system_id:
            self.system_id = system_id = self._gnss_system(system_id)
        probe = TlogReader(path, system_id, peek=False)
        try:
            for n, _ in enumerate(probe.samples()):
                if probe.utc_offset_us is not None or n >= self.PEEK_SAMPLES:
                    break
            self.utc_offset_us = probe.utc_offset_us
            # GPS_RAW_INT carries no GNSS time: the clock is checked against the receiver's motion,
            # or where the vehicle did not go far enough for that, against its epochs
            track = list(probe.track())
            clock = motion_clock(track, self.notes) or epoch_clock([f[0] for f in track], self.notes)
            self.clock = None if clock is None else (0, clock[1])      # rescaled about the boot
        finally:
            probe.close()

    def close(self) -> None:
        self._file.close()

    def _gnss_system(self, wanted: int) -> int:
        """The system to read: `wanted`, unless it sends no 3D fix in this log and another does (an
        autopilot whose SYSID_THISMAV is not 1; a log of several vehicles): then the one that sends
        the most, and that is said. A tlog is read after the flight, when its autopilot cannot be asked.
        The scan stops at the first fix from `wanted`: a log of the system asked for costs little."""
        senders: Counter[int] = Counter()      # 3D fixes per system
        probe = TlogReader(self.path, 0, peek=False)
        try:
            for system, _ in probe._fixes():
                if system == wanted:
                    return wanted
                senders[system] += 1
        finally:
            probe.close()
        if not senders:
            return wanted
        chosen, n = senders.most_common(1)[0]
        others = sorted(s for s in senders if s != chosen)
        self.notes.append(f"system {wanted} sends no GNSS fix in this log: reading system {chosen}, which sends {n}"
                          + (f" (systems {', '.join(map(str, others))} send some too)" if others else "")
                          + "; --system-id N reads system N, 0 every system")
        return chosen

    def _fixes(self) -> Iterator[tuple[int, GnssFix]]:
        """(sending system, fix) of every 3D fix, GPS_RAW_INT alone decoded."""
        if self.size == 0:
            return
        with mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            for msg in self._frames(buf, GNSS_ONLY):
                fix, _ = to_sample(msg)
                if isinstance(fix, GnssFix) and fix.fix_ok:
                    yield msg.get_srcSystem(), fix

    def track(self) -> Iterator[tuple[int, float, float, float | None, float | None]]:
        """(t_us, lat, lon, v_n, v_e) of every 3D fix (v None: none sent)."""
        for _, fix in self._fixes():
            yield fix.t_us, fix.lat_deg, fix.lon_deg, fix.vel_n_mps, fix.vel_e_mps

    def samples(self) -> Iterator[Sample]:
        repeats, fixes = CompassRepeats(), UnixFixes(self.notes.append)
        imu_stream = ImuStream(self.notes.append)
        for msg in self:
            if (kind := msg.get_type()) in IMU_MESSAGES and not imu_stream(kind):
                self.skipped["imu_other_stream"] += 1
                continue
            sample, reason = to_sample(msg)
            if isinstance(sample, ImuSample):
                sample = repeats(sample)        # a slower compass's reading, once
                fixes.imu(sample.t_us, self.last_time_us)
            elif isinstance(sample, GnssFix):
                sample = fixes.fix(sample, self.last_time_us)     # a fix in UNIX time, on the boot clock
            if sample is not None and self.clock is not None and hasattr(sample, "t_us"):
                # on the receiver's time (guard.sources.clock), about the boot: every stream alike
                sample = dataclasses.replace(sample, t_us=self.on_clock(sample.t_us))
            if sample is not None:
                if self.utc_offset_us is None and isinstance(sample, ImuSample) and sample.t_us < T_MIN_US:
                    # the ground station's clock at the first IMU sample: UTC for the log (its latency aside)
                    self.utc_offset_us = self.last_time_us - sample.t_us
                yield sample
            elif reason:
                self.skipped[reason] += 1

    def __iter__(self) -> Iterator:
        """Yield decoded messages of the WANTED types (others are only counted)."""
        if self.size == 0:
            return
        with mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            yield from self._frames(buf, WANTED)

    def _frames(self, buf, wanted) -> Iterator:
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
            if msgid not in wanted and plausible:
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
            if msgid not in wanted:
                pos = end
                continue
            if self.system_id and sysid != self.system_id:
                if msgid != mavlink.MAVLINK_MSG_ID_HEARTBEAT:    # a heartbeat is no data: a ground station's
                    skip["other_system"] += 1                  # (every tlog a ground station records has them)
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
    return reader.samples()
