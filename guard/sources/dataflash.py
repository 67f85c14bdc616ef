"""ArduPilot DataFlash logs (.bin): the autopilot's own log, read with pymavlink's DFReader.

The format (ArduPilot `libraries/AP_Logger/LogStructure.h`, pymavlink `DFReader.py`): messages
`0xA3 0x95 <type>` + a packed little-endian body, with no checksum; FMT messages (type 128) declare
each type's name, format characters and columns. Units, as ArduPilot logs them:
- time: `TimeUS`, microseconds since boot (older logs: `TimeMS` ms; their GPS has boot ms in `T` and
  GPS time of week in `TimeMS`/`Week`). All samples are on this one time base.
- IMU (IMU, IMU2.. or an instance column `I`): GyrX..Z rad/s, AccX..Z m/s^2 specific force (about
  -9.8 on z at rest), body frame x forward, y right, z down (FRD), corrected and rotated to the body.
- MAG: MagX..Z milligauss (int16), body frame, offsets applied. All zero: no compass.
- GPS: Status (AP_GPS::GPS_Status, 3 = 3D fix and better), GWk/GMS GPS week and ms of week, Lat/Lng
  degE7, Alt cm, Spd m/s, GCrs deg (ground course), VZ m/s. GPA (written with the same TimeUS):
  HAcc m and SAcc m/s, stored in cm ('C').
- ATT: Roll, Pitch in centidegrees ('c').
- XKF4 (EKF3), NKF4 (EKF2), EKF4 (EKF1): SV, SP, SH, SM (EKF1: SMX..SMZ), SVT: the square roots of
  the EKF's innovation test ratios of GNSS velocity, GNSS position, height, magnetometer and
  airspeed, x100 ('c'); above 1 the measurement failed its gate. Core/lane 0 (`C` = 0 where the
  column exists; older logs write core 1 as NKF9/XKF9).

How it is read: `DFReader_binary` frames the file, parses the FMT messages and indexes the offset
of every message per type. guard then decodes only the types it needs from that index, with the
struct formats and multipliers DFReader built from the FMT messages: DFMessage attribute access
runs at about 40 k messages/s, struct on the index at about 1 M/s. Three things are changed in
DFReader, by subclassing: its C fast indexer is replaced by its Python twin (pymavlink's current
`dfindexer.c` calls exit() on an undeclared type or an FMT of length < 3), an FMT declaring a
length below 3 is refused (DFReader frames by that length; 0 makes it loop forever:
`bad_format`), and its GPS clock, which guard does not use, is skipped (it parses the whole file
when a log has no GPS). DFReader prints what it skips: that is captured and logged at debug level.

Damage, as DFReader meets it (a DataFlash message has no checksum): a cut last message is dropped
(`skipped["truncated"]`); garbage between messages is skipped up to the next header
(`garbage_bytes`); a header of a type no FMT declared stops DFReader's indexer, and the rest of the
file is not read (`unread_bytes`, and a note). Values out of any sensor's range, time stamps beyond
~116 days of boot, a GPS status above 8 are corrupt messages (`bad_message`).
"""

from __future__ import annotations

import contextlib
import datetime
import heapq
import logging
import math
import re
import statistics
import struct
from collections.abc import Callable, Iterator
from itertools import repeat

from pymavlink import DFReader

from guard.errors import SourceError
from guard.model.samples import Attitude, GnssFix, ImuSample, Sample, VehicleType
from guard.sources.base import LogSource

log = logging.getLogger(__name__)

HEAD = b"\xa3\x95"
FMT_TYPE = 0x80
MAG_FRESH_US = 500_000            # a MAG reading older than this is not attached to an IMU sample
MAX_BOOT_US = 10**13              # ~116 days: a larger boot time stamp is corrupt data
MAX_ACC_MPS2, MAX_GYRO_RADPS = 2000.0, 200.0     # beyond any MEMS range: corrupt data
MAX_SPEED_MPS = 600.0             # beyond a GNSS receiver's export limit: corrupt data
GPS_EPOCH = datetime.datetime(1980, 1, 6, tzinfo=datetime.timezone.utc)
LEAP_SECONDS = 18
EPISODE_GAP_US = 1_000_000        # test ratios above 1 less than this apart are one episode
MAX_VERDICTS = 200
EKF_TESTS = {"SV": "gnss_vel", "SP": "gnss_pos", "SH": "height", "SM": "mag", "SMX": "mag", "SMY": "mag",
             "SMZ": "mag", "SVT": "airspeed"}
EKF_TYPES = {"XKF4": "EKF3", "NKF4": "EKF2", "EKF4": "EKF1"}
ERR_GPS = {11: "GPS", 7: "GPS failsafe"}       # LogErrorSubsystem
GPS_INFO = re.compile(r"detected|HW:|SW:|baud", re.IGNORECASE)     # receiver identification, not a finding
FIRMWARE = re.compile(r"^(?:Ardu|APM:?)\s*(Rover|Copter|Plane|Sub|Heli|Blimp)", re.IGNORECASE)
BUILD_GROUND = {1: True, 2: False, 3: False, 7: False, 12: False, 13: False}   # VER.BU: Rover, Copter, ...


def looks_like_dataflash(head: bytes) -> bool:
    """A DataFlash log starts with a message header and an FMT message (type 128)."""
    return len(head) >= 5 and head[:3] == HEAD + bytes((FMT_TYPE,)) and head[4] >= 4


class _Formats(dict):
    """DFReader's table of formats, refusing an FMT whose length is shorter than a header: DFReader
    frames messages by that length, and a corrupt one of 0 makes its indexer loop forever. (A length
    that disagrees with the format is kept: ArduCopter 3.4 declares BAR3 4 bytes longer than its
    format, and its messages are framed by the length.)"""

    refused = 0

    def __setitem__(self, mtype, fmt) -> None:
        if fmt.len < 3:
            self.refused += 1
            return
        super().__setitem__(mtype, fmt)


class _Index(DFReader.DFReader_binary):
    """DFReader's binary reader with its pure-Python indexer, checked formats and no GPS clock."""

    def init_arrays(self, progress_callback=None):
        self.formats = _Formats(self.formats)
        super().init_arrays(progress_callback)

    def init_arrays_fast(self, progress_callback=None):
        self.init_arrays(progress_callback)

    def init_clock(self):
        self.clock = None


class _Counter:
    """A file-like sink for what DFReader prints: counts lines, keeps the first few."""

    def __init__(self):
        self.lines = 0
        self.first: list[str] = []

    def write(self, text: str) -> int:
        for line in text.splitlines():
            if line.strip():
                self.lines += 1
                if len(self.first) < 5:
                    self.first.append(line.strip())
        return len(text)

    def flush(self) -> None:
        """Nothing buffered."""


def _open_index(path: str) -> _Index:
    """DFReader's index of the log at `path`; a SourceError naming the file if it cannot be made."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as e:
        raise SourceError(f"{path}: cannot open: {e.strerror}") from None
    if not looks_like_dataflash(head):
        raise SourceError(f"{path}: not a DataFlash log (no FMT message at its start)")
    said = _Counter()
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            index = _Index(path)
    except Exception as e:      # noqa: BLE001 - DFReader raises anything on a corrupt FMT; one line for the user
        raise SourceError(f"{path}: DataFlash log not readable: {_one_line(e)}") from None
    if said.lines:
        log.debug("%s: DFReader said %d lines, first: %s", path, said.lines, "; ".join(said.first))
    return index


def _one_line(e: Exception) -> str:
    """An exception as one printable line (a corrupt format character can be a newline)."""
    return f"{type(e).__name__}: " + repr(str(e))[1:-1]


def _time_column(fmt) -> tuple[str, int] | None:
    """The boot-time column of a format and its scale to microseconds."""
    if "TimeUS" in fmt.colhash:
        return "TimeUS", 1
    if fmt.name.startswith("GPS") and "T" in fmt.colhash:       # old GPS: TimeMS is the GPS time of week
        return "T", 1000
    if "TimeMS" in fmt.colhash:
        return "TimeMS", 1000
    return None


def _instance_number(name: str, base: str) -> int | None:
    """IMU -> 0, IMU2 -> 1, IMU3 -> 2 (older logs' instances); None: not an instance of base."""
    if name == base:
        return 0
    rest = name[len(base):]
    return int(rest) - 1 if name.startswith(base) and rest.isdigit() and int(rest) >= 2 else None


def _rate_hz(times: list[int]) -> float | None:
    """A stream's rate from the median interval between its messages (robust to gaps and bursts)."""
    steps = [b - a for a, b in zip(times, times[1:]) if b > a]
    return round(1e6 / statistics.median(steps), 1) if steps else None


def _episodes(rows: Iterator[tuple[int, float]]) -> Iterator[tuple[int, int, float]]:
    """(start, end, peak) of the runs of ratios above 1.0, runs less than EPISODE_GAP_US apart merged."""
    ep = None
    for t, ratio in rows:
        if ratio <= 1.0:
            continue
        if ep is not None and t - ep[1] <= EPISODE_GAP_US:
            ep = (ep[0], t, max(ep[2], ratio))
            continue
        if ep is not None:
            yield ep
        ep = (t, t, ratio)
    if ep is not None:
        yield ep


class _Log:
    """Rows of chosen message types, decoded from DFReader's index with DFReader's formats."""

    def __init__(self, index: _Index):
        self.index = index
        self.data = index.data_map
        self.size = index.data_len

    def format(self, name: str):
        t = self.index.name_to_id.get(name)
        return None if t is None else self.index.formats.get(t)

    def offsets(self, name: str) -> list[int]:
        """Offsets of the complete messages of a type, in file order."""
        fmt = self.format(name)
        if fmt is None:
            return []
        offs = self.index.offsets[fmt.type]
        return offs[:-1] if offs and offs[-1] + fmt.len > self.size else offs

    def decoder(self, name: str, columns: list[str]) -> Callable[[int], tuple]:
        """A function: offset -> (boot time in us, then the values of `columns`, scaled by their
        format's multiplier; None for a column the format lacks)."""
        fmt = self.format(name)
        time_col, scale = _time_column(fmt) or (None, 0)
        unpack, data = struct.Struct(fmt.msg_struct).unpack_from, self.data
        picks = [(i, None if i is None else fmt.msg_mults[i]) for i in map(fmt.colhash.get, columns)]
        it = fmt.colhash.get(time_col) if time_col else None

        def decode(ofs: int) -> tuple:
            e = unpack(data, ofs + 3)
            t = -1 if it is None else e[it] * scale
            return (t, *(None if i is None else e[i] * m if m else e[i] for i, m in picks))
        return decode

    def split(self, name: str, column: str) -> dict[int, list[int]]:
        """Offsets of a type's messages by the value of a one-byte column (an instance, an EKF core)."""
        fmt = self.format(name)
        i = fmt.colhash[column]
        k = 3 + struct.calcsize("<" + "".join(DFReader.FORMAT_TO_STRUCT[c][0] for c in fmt.format[:i]))
        data, out = self.data, {}
        for o in self.offsets(name):
            if o + k < self.size:
                out.setdefault(data[o + k], []).append(o)
        return out

    def instances(self, base: str) -> dict[int, tuple[str, list[int]]]:
        """(type name, offsets) of each instance of a sensor: IMU, IMU2, IMU3 or IMU rows by `I`."""
        out: dict[int, tuple[str, list[int]]] = {}
        for name in sorted(self.index.name_to_id):
            n = _instance_number(name, base)
            if n is None or not self.offsets(name):
                continue
            if "I" in self.format(name).colhash:
                out.update((i, (name, offs)) for i, offs in self.split(name, "I").items())
            else:
                out[n] = (name, self.offsets(name))
        return out

    def rows(self, name: str, columns: list[str], offsets: list[int] | None = None) -> Iterator[tuple]:
        """Decoded rows (time, *columns) of a type, all or at `offsets`; a row that cannot be
        unpacked (a format longer than its declared length, at the end of the file) is left out."""
        decode = self.decoder(name, columns)
        for o in self.offsets(name) if offsets is None else offsets:
            try:
                yield decode(o)
            except struct.error:
                continue

    def times(self, name: str, offsets: list[int]) -> list[int]:
        return [row[0] for row in self.rows(name, [], offsets)]

    def texts(self, name: str, column: str) -> Iterator[tuple[int, str]]:
        if self.format(name) is not None and column in self.format(name).colhash:
            for t, text in self.rows(name, [column]):
                yield t, DFReader.null_term(text)


class DataFlashReader(LogSource):
    """Samples of an ArduPilot DataFlash log: GPS, IMU (+ the latest MAG), ATT and the vehicle type.

    `imu` and `gnss` pick an instance (default 0, the primary); `system_id` is accepted and ignored
    (a DataFlash log holds one vehicle). Opening surveys the log: rates, other instances, the date,
    the vehicle and the autopilot's own verdicts; `samples()` then decodes the streams in file order.
    """

    def __init__(self, path: str, system_id: int = 0, imu: int | None = None, gnss: int | None = None):
        super().__init__()
        self.path = path
        self._index = _open_index(path)
        self._log = _Log(self._index)
        self.size, self.position = self._index.data_len, 0
        self.ground: bool | None = None         # the vehicle class, from the firmware string
        self._mag_now: tuple | None = None      # the latest MAG reading: (t_us, x, y, z gauss)
        try:
            self._survey(imu, gnss)
        except SourceError:
            self.close()
            raise
        except Exception as e:      # noqa: BLE001 - a format too damaged to survey: one line for the user
            self.close()
            raise SourceError(f"{path}: DataFlash log not readable: {_one_line(e)}") from None

    def close(self) -> None:
        self._index.close()

    def _survey(self, imu: int | None, gnss: int | None) -> None:
        idx = self._index
        self.messages.update({idx.formats[t].name: len(offs) for t, offs in enumerate(idx.offsets)
                              if offs and t in idx.formats})
        self._account()
        self.ground = self._vehicle()
        self._imu_n, self._imu = self._choose("IMU", imu, "--imu")
        self._gnss_n, self._gnss = self._choose("GPS", gnss, "--gnss")
        self._mag = self._log.instances("MAG").get(0)
        self._att = ("ATT", self._log.offsets("ATT")) if self._log.offsets("ATT") else None
        self._accuracy = self._accuracies()
        self.date = self._date()
        used = [(f"IMU {self._imu_n}", self._imu), (f"GPS {self._gnss_n}", self._gnss), ("MAG", self._mag),
                ("ATT", self._att)]
        rates = [f"{label}: {self._rate(s)} Hz" for label, s in used if s is not None]
        if rates:
            self.notes.insert(0, ", ".join(rates))
        self.verdicts = self._ekf_verdicts() + self._message_verdicts()
        self.verdicts.sort(key=lambda v: v["time_usec"])
        if len(self.verdicts) > MAX_VERDICTS:
            self.notes.append(f"{len(self.verdicts)} autopilot verdicts, the first {MAX_VERDICTS} listed")
            del self.verdicts[MAX_VERDICTS:]

    def _rate(self, stream: tuple[str, list[int]]) -> float | None:
        return _rate_hz(self._log.times(*stream))

    def _account(self) -> None:
        """Count what DFReader could not frame: a cut last message, garbage, a tail it did not read."""
        idx, size = self._index, self._index.data_len
        spans, stop = 0, 0
        for t, offs in enumerate(idx.offsets):
            if not offs or t not in idx.formats:
                continue
            length = idx.formats[t].len
            spans += length * len(offs)
            if offs[-1] + length > size:        # the last message, cut: only its first bytes are there
                self.skipped["truncated"] += 1
                spans -= offs[-1] + length - size
            stop = max(stop, offs[-1] + length)
        garbage = min(stop, size) - spans
        if garbage > 0:
            self.skipped["garbage_bytes"] += garbage
        if idx.formats.refused:
            self.skipped["bad_format"] += idx.formats.refused
        tail = size - stop
        if tail >= 3 and self._index.data_map[stop:stop + 2] == HEAD:
            self.skipped["unread_bytes"] += tail
            self.notes.append(f"reading stopped at byte {stop} of {size}: a message type no FMT declared "
                              f"(corrupt data); the last {tail} bytes are not read")
        elif tail >= 3:
            self.skipped["garbage_bytes"] += tail

    def _vehicle(self) -> bool | None:
        """Ground vehicle or not, from the firmware string (MSG) or the build type (VER.BU)."""
        for _, text in self._log.texts("MSG", "Message"):
            if m := FIRMWARE.match(text):
                ground = m.group(1).lower() == "rover"
                self.notes.append(f"autopilot: {text}")
                return ground
        if self._log.format("VER") is not None and "BU" in self._log.format("VER").colhash:
            for _, build in self._log.rows("VER", ["BU"]):
                return BUILD_GROUND.get(build)
        return None

    def _choose(self, base: str, wanted: int | None, option: str) -> tuple[int | None, tuple | None]:
        """The instance wanted (default: the primary) and its stream (type name, offsets); a note on
        the others."""
        found = self._log.instances(base)
        n = min(found, default=None) if wanted is None else wanted
        if wanted is not None and wanted not in found:
            have = ", ".join(str(i) for i in sorted(found)) or "none"
            raise SourceError(f"{self.path}: no {base} {wanted} in this log ({base} instances: {have})")
        if n is None:
            self.notes.append(f"no {base} messages in this log")
            return None, None
        for i in sorted(set(found) - {n}):
            self.notes.append(f"also {base} {i} at {self._rate(found[i])} Hz, not used: {option} {i} to replay it")
        return n, found[n]

    def _accuracies(self) -> dict[int, tuple[float | None, float | None]]:
        """GPA's horizontal and speed accuracy (m, m/s) by time stamp, for the GPS instance used
        (ArduPilot writes GPS and GPA with one time stamp)."""
        if self._gnss is None:
            return {}
        n = self._gnss_n
        gpa = self._log.instances("GPA").get(n)
        if gpa is None:
            return {}
        return {t: (h if h else None, s if s else None) for t, h, s in self._log.rows(gpa[0], ["HAcc", "SAcc"], gpa[1])}

    def _date(self) -> datetime.date | None:
        """The UTC day of the first GPS message with a fix (GWk/GMS; older logs Week/TimeMS)."""
        if self._gnss is None:
            return None
        name, offs = self._gnss
        cols = self._log.format(name).colhash
        week, ms = ("GWk", "GMS") if "GWk" in cols else ("Week", "TimeMS") if "Week" in cols else (None, None)
        if week is None:
            return None
        for _, status, wk, wms in self._log.rows(name, ["Status", week, ms], offs):
            if status is not None and wk is not None and status >= 3 and 0 < wk < 10_000:
                gps = GPS_EPOCH + datetime.timedelta(weeks=wk, milliseconds=wms)
                return (gps - datetime.timedelta(seconds=LEAP_SECONDS)).date()
        return None

    # -- the autopilot's own verdicts ----------------------------------------------------------
    def _ekf_verdicts(self) -> list[dict]:
        """One record per episode of an EKF innovation test ratio above 1 (core 0)."""
        out = []
        for name, source in EKF_TYPES.items():
            fmt = self._log.format(name)
            if fmt is None or not self._log.offsets(name):
                continue
            offs = self._log.split(name, "C").get(0, []) if "C" in fmt.colhash else self._log.offsets(name)
            cols = [c for c in EKF_TESTS if c in fmt.colhash]
            rows = [r for r in self._log.rows(name, cols, offs) if 0 <= r[0] < MAX_BOOT_US]
            for test in dict.fromkeys(EKF_TESTS[c] for c in cols):
                k = [i + 1 for i, c in enumerate(cols) if EKF_TESTS[c] == test]
                ratios = ((r[0], max(r[i] for i in k)) for r in rows)
                out += [{"time_usec": int(a), "end_usec": int(b), "source": source, "test": test,
                         "peak_ratio": round(peak, 2)} for a, b, peak in _episodes(ratios)]
        return out

    def _message_verdicts(self) -> list[dict]:
        """The autopilot's messages about GPS: MSG texts naming it, ERR of the GPS subsystems."""
        out = [{"time_usec": int(t), "source": "autopilot", "test": "message", "text": text}
               for t, text in self._log.texts("MSG", "Message") if "GPS" in text and not GPS_INFO.search(text)]
        fmt = self._log.format("ERR")
        if fmt is not None and {"Subsys", "ECode"} <= set(fmt.colhash):
            for t, subsys, code in self._log.rows("ERR", ["Subsys", "ECode"]):
                if subsys in ERR_GPS:
                    what = "resolved" if code == 0 else "glitch" if (subsys, code) == (11, 2) else f"error {code}"
                    out.append({"time_usec": int(t), "source": "autopilot", "test": "message",
                                "text": f"ERR {ERR_GPS[subsys]}: {what}"})
        return out

    # -- samples -----------------------------------------------------------------------------------
    def samples(self) -> Iterator[Sample]:
        if self.ground is not None:     # the whole log's vehicle, before its first sample
            yield VehicleType(self.ground)
        self._mag_now = None
        streams = [(s, convert, cols) for s, convert, cols in (
            (self._gnss, self._gnss_sample, ["Status", "Lat", "Lng", "Alt", "Spd", "GCrs"]),
            (self._imu, self._imu_sample, ["AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ"]),
            (self._mag, self._mag_reading, ["MagX", "MagY", "MagZ"]),
            (self._att, self._attitude, ["Roll", "Pitch"])) if s is not None]
        steps = [(self._log.decoder(s[0], cols), convert) for s, convert, cols in streams]
        merged = heapq.merge(*(zip(s[1], repeat(k)) for k, (s, _, _) in enumerate(streams)))
        last, backwards = -1, 0
        for ofs, k in merged:
            self.position = ofs
            decode, convert = steps[k]
            try:
                values = decode(ofs)
                sample, reason = convert(values) if 0 <= values[0] < MAX_BOOT_US else (None, "bad_message")
            except (struct.error, TypeError):   # a format longer than its length; a column it lacks
                sample, reason = None, "bad_message"
            if reason:
                self.skipped[reason] += 1
            if sample is None:
                continue
            backwards += sample.t_us < last - 1000
            last = sample.t_us
            self.first_time_us = sample.t_us if self.first_time_us is None else self.first_time_us
            self.last_time_us = sample.t_us
            yield sample
        self.position = self.size
        if backwards:
            self.notes.append(f"{backwards} samples earlier than the one before them (file order kept)")

    def _gnss_sample(self, v: tuple) -> tuple[GnssFix | None, str | None]:
        t, status, lat, lon, alt, speed, course = v
        if not (0 <= status <= 8 and math.isfinite(alt)):
            return None, "bad_message"
        fix = status >= 3
        if fix and not (abs(lat) <= 90 and abs(lon) <= 180 and (lat, lon) != (0.0, 0.0)):
            return None, "gnss_bad_position"
        vn = ve = None
        if speed is not None and course is not None and math.isfinite(speed) and math.isfinite(course):
            if not (0.0 <= speed < MAX_SPEED_MPS and abs(course) <= 360.0):
                return None, "bad_message"
            c = math.radians(course)
            vn, ve = speed * math.cos(c), speed * math.sin(c)
        h_acc, vel_acc = self._accuracy.get(t, (None, None))
        return GnssFix(int(t), fix, lat, lon, alt, vn, ve, h_acc, vel_acc), None

    def _imu_sample(self, v: tuple) -> tuple[ImuSample | None, str | None]:
        t, ax, ay, az, gx, gy, gz = v
        a, w = MAX_ACC_MPS2, MAX_GYRO_RADPS
        if not (abs(ax) <= a and abs(ay) <= a and abs(az) <= a and abs(gx) <= w and abs(gy) <= w and abs(gz) <= w):
            return None, "bad_message"      # also NaN: every comparison with NaN is False
        mag = self._mag_now
        if mag is None or abs(t - mag[0]) >= MAG_FRESH_US:
            return ImuSample(int(t), ax, ay, az, gx, gy, gz, None, None, None), None
        return ImuSample(int(t), ax, ay, az, gx, gy, gz, mag[1], mag[2], mag[3]), None

    def _mag_reading(self, v: tuple) -> tuple[None, None]:
        t, mx, my, mz = v
        self._mag_now = None if (mx, my, mz) == (0, 0, 0) else (t, mx / 1000.0, my / 1000.0, mz / 1000.0)
        return None, None

    def _attitude(self, v: tuple) -> tuple[Attitude | None, str | None]:
        t, roll, pitch = v
        if roll is None or pitch is None:
            return None, "bad_message"
        roll, pitch = math.radians(roll), math.radians(pitch)
        if not (math.isfinite(roll) and math.isfinite(pitch)) or abs(pitch) > 1.5:
            return None, "attitude_non_finite"
        return Attitude(int(t), roll, pitch), None
