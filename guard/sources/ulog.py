"""PX4 ULog files (.ulg), read with pyulog: the autopilot's own topics, already in SI units.

Time base: every record's `timestamp`, microseconds since the autopilot booted (one clock for all
topics, PX4's hrt). Units and frames, from PX4's msg definitions (msg/*.msg):
- `vehicle_gps_position` / `sensor_gps` (GNSS): older layout lat/lon int32 degE7 and alt int32 mm
  (MSL); newer layout latitude_deg/longitude_deg float64 and altitude_msl_m; told apart by their field
  names. vel_n_m_s, vel_e_m_s m/s; fix_type >= 3 is a 3D fix; eph is the receiver's horizontal
  accuracy in metres (u-blox hAcc, not a DOP); s_variance_m_s is, despite its name, a 1-sigma speed
  accuracy in m/s (u-blox sAcc; EKF2 squares it). time_utc_usec: UTC, 0 before the receiver knows it.
- `sensor_combined` (IMU the autopilot selected): gyro_rad rad/s, accelerometer_m_s2 specific force
  m/s^2 (about -9.8 on z at rest), body FRD; `timestamp` is the gyro's sample time, the
  accelerometer's is timestamp + accelerometer_timestamp_relative (0x7fffffff: no valid sample).
  `vehicle_imu` instance N (imu=N): delta_angle rad and delta_velocity m/s over delta_*_dt us.
- `vehicle_magnetometer`: magnetometer_ga, gauss, body FRD; attached to an IMU sample when under 0.5 s old.
- `vehicle_attitude`: q = (w, x, y, z), rotation from body FRD to NED: roll and pitch in radians.
- `vehicle_status`: system_type (the MAVLink MAV_TYPE of its HEARTBEAT) or vehicle_type (1 rotary
  wing, 2 fixed wing, 3 rover, 4 airship) or, in old logs, is_rotary_wing.
- PX4's own findings, as `verdicts`: EKF2's innovation test ratios (`estimator_innovation_test_ratios`,
  the first component of a vector; older logs: `estimator_status`'s *_test_ratio) above 1, and the
  autopilot's text messages about GPS.

pyulog reads the whole file at once and prints what it finds wrong on stdout (which would corrupt
`guard replay --report -`): its output is caught and logged. It stops silently at a cut message;
the reader notices (the last read came up short) and counts it. Records whose time stamp is
implausible or out of order (corrupt bytes) or whose values are not physical are counted and dropped.
"""

from __future__ import annotations

import contextlib
import datetime
import io
import logging
import os
import re
from bisect import bisect_right
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from pyulog import ULog
from pyulog.exceptions import ULogException

from guard.errors import SourceError
from guard.model.samples import Attitude, GnssFix, ImuSample, Sample, VehicleType
from guard.sources.base import LogSource

log = logging.getLogger(__name__)

MAGIC = b"ULog\x01\x12\x35"
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")
TOPICS = [*GPS_TOPICS, "sensor_combined", "vehicle_imu", "vehicle_magnetometer", "vehicle_attitude",
          "vehicle_status", "estimator_innovation_test_ratios", "estimator_status"]
MAG_MAX_AGE_US = 500_000
MAX_BOOT_TIME_US = 30 * 86_400_000_000      # a time stamp past 30 days of uptime is corrupt bytes
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
GYRO_MAX_RADPS, ACC_MAX_MPS2, MAG_MAX_GAUSS = 100.0, 1000.0, 10.0   # beyond any MEMS sensor's range
SPEED_MAX_MPS, ACCURACY_MAX = 600.0, 1e4    # beyond a GNSS receiver's limits (m/s; m and m/s)
MAV_TYPE_GROUND_ROVER, VEHICLE_TYPE_ROVER = 10, 3
CHUNK = 4096
MAX_PYULOG_LINES = 5                        # what pyulog prints about a corrupt file, logged (the rest counted)
GPS_TEXT = re.compile(r"gps|gnss", re.IGNORECASE)
# EKF2 test -> its innovation test ratio fields (estimator_innovation_test_ratios), older estimator_status's
RATIO_FIELDS = {"gnss_vel": ("gps_hvel[0]", "gps_vvel"), "gnss_pos": ("gps_hpos[0]",),
                "height": ("baro_vpos", "gps_vpos"), "mag": ("mag_field[0]", "heading")}
STATUS_FIELDS = {"gnss_vel": ("vel_test_ratio",), "gnss_pos": ("pos_test_ratio",), "height": ("hgt_test_ratio",),
                 "mag": ("mag_test_ratio", "hdg_test_ratio")}


def looks_like_ulog(head: bytes) -> bool:
    """A ULog file starts with "ULog", 0x01 0x12 0x35 (then its version and start time)."""
    return head[:7] == MAGIC


@dataclass(frozen=True)
class Stream:
    """One topic's samples as columns (the first is the time stamp, us); `make` builds a sample from a row."""

    topic: str
    columns: tuple[np.ndarray, ...]
    make: Callable[[tuple], Sample]

    @property
    def t_us(self) -> np.ndarray:
        return self.columns[0]

    def rows(self) -> Iterator[tuple]:
        for a in range(0, len(self.t_us), CHUNK):
            yield from zip(*(c[a:a + CHUNK].tolist() for c in self.columns))


class _TrackedFile:
    """The file as pyulog reads it. `cut_at`: where its last non-empty read began if that read came up
    short (pyulog stops there silently: a file cut inside a message, or corrupt bytes read as a long one)."""

    def __init__(self, f):
        self._f, self.cut_at = f, None

    def read(self, n: int = -1) -> bytes:
        at = self._f.tell()
        data = self._f.read(n)
        if data:
            self.cut_at = at if 0 <= n and len(data) < n else None
        return data

    def seek(self, *args) -> int:
        return self._f.seek(*args)

    def tell(self) -> int:
        return self._f.tell()

    def close(self) -> None:
        """pyulog closes its file when done; the reader closes its own."""


def _load(path: str) -> tuple[ULog, int | None]:
    """pyulog's reading of the topics guard uses, and the offset where it stopped short (None: at the end)."""
    try:
        f = open(path, "rb")
    except OSError as e:
        raise SourceError(f"{path}: cannot open: {e.strerror}") from None
    said = io.StringIO()
    with f, contextlib.redirect_stdout(said):
        tracked = _TrackedFile(f)
        try:
            ulog = ULog(tracked, message_name_filter_list=TOPICS)
        except ULogException as e:
            raise SourceError(f"{path}: not a ULog file guard can read ({e})") from None
        except OSError as e:
            raise SourceError(f"{path}: cannot read: {e.strerror}") from None
        except Exception as e:      # noqa: BLE001 - pyulog parses untrusted bytes: anything it raises means unreadable
            raise SourceError(f"{path}: cannot be read as ULog ({type(e).__name__}: {e})") from None
    lines = [line for line in said.getvalue().splitlines() if line.strip()]
    for line in lines[:MAX_PYULOG_LINES]:
        log.warning("%s: pyulog: %s", path, line)
    if len(lines) > MAX_PYULOG_LINES:
        log.warning("%s: pyulog: %d more lines like these", path, len(lines) - MAX_PYULOG_LINES)
    return ulog, tracked.cut_at


def _in_order(t: np.ndarray) -> np.ndarray:
    """Mask of the longest non-decreasing sequence of time stamps: corrupt ones are out of order."""
    if t.size < 2 or bool(np.all(t[1:] >= t[:-1])):
        return np.ones(t.size, bool)
    tails: list[int] = []           # smallest last time of a sequence of each length, and its index
    tails_at: list[int] = []
    prev = [-1] * t.size
    for i, x in enumerate(t.tolist()):
        k = bisect_right(tails, x)
        prev[i] = tails_at[k - 1] if k else -1
        if k == len(tails):
            tails.append(x)
            tails_at.append(i)
        else:
            tails[k], tails_at[k] = x, i
    keep = np.zeros(t.size, bool)
    i = tails_at[-1]
    while i >= 0:
        keep[i] = True
        i = prev[i]
    return keep


def _timed(data, skipped) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A dataset's columns restricted to its records with plausible, ordered time stamps, and those."""
    t = data.data["timestamp"].astype(np.int64, copy=False)
    ok = (t >= 0) & (t <= MAX_BOOT_TIME_US)
    ok[ok] = _in_order(t[ok])
    if not ok.all():
        skipped["ulog_bad_time"] += int((~ok).sum())
    return {k: v[ok] for k, v in data.data.items()}, t[ok]


def _drop(mask: np.ndarray, reason: str, skipped) -> np.ndarray:
    """`mask` (True: keep), counting the records it drops under `reason`."""
    if not mask.all():
        skipped[reason] += int((~mask).sum())
    return mask


def _vec(d: dict, name: str) -> list[np.ndarray]:
    return [d[f"{name}[{i}]"].astype(np.float64) for i in range(3)]


def _none_if_nan(x: float) -> float | None:
    return None if x != x else x


def gnss_stream(data, skipped) -> Stream | None:
    """GnssFix from either layout of vehicle_gps_position / sensor_gps (None: neither layout)."""
    d, t = _timed(data, skipped)
    if "latitude_deg" in d:
        lat, lon, alt = (d[k].astype(np.float64) for k in ("latitude_deg", "longitude_deg", "altitude_msl_m"))
    elif "lat" in d:
        lat, lon = d["lat"] * 1e-7, d["lon"] * 1e-7
        alt = d["alt"] / 1000.0
    else:
        return None
    nan = np.full(t.size, np.nan)
    fix_ok = d["fix_type"] >= 3
    good = ~fix_ok | ((np.abs(lat) <= 90) & (np.abs(lon) <= 180) & ((lat != 0) | (lon != 0)) & np.isfinite(alt))
    keep = _drop(good, "gnss_bad_position", skipped)
    vn, ve = (d.get(k, nan).astype(np.float64) for k in ("vel_n_m_s", "vel_e_m_s"))
    vel_ok = (d["vel_ned_valid"] != 0) if "vel_ned_valid" in d else np.isfinite(vn)
    physical = (np.abs(vn) < SPEED_MAX_MPS) & (np.abs(ve) < SPEED_MAX_MPS)     # False for NaN
    vel_ok &= _drop(physical | ~vel_ok, "gnss_bad_velocity", skipped)
    vn, ve = np.where(vel_ok, vn, np.nan), np.where(vel_ok, ve, np.nan)
    h_acc, vel_acc = (d.get(k, nan).astype(np.float64) for k in ("eph", "s_variance_m_s"))
    h_acc, vel_acc = (np.where((a > 0) & (a < ACCURACY_MAX), a, np.nan) for a in (h_acc, vel_acc))
    cols = tuple(c[keep] for c in (t, fix_ok, lat, lon, alt, vn, ve, h_acc, vel_acc))

    def make(r):
        return GnssFix(r[0], r[1], r[2], r[3], r[4], *map(_none_if_nan, r[5:]))
    return Stream(data.name, cols, make)


def imu_stream(data, mag, skipped) -> Stream:
    """ImuSample from sensor_combined, or from vehicle_imu's increments, with the latest magnetometer."""
    d, t = _timed(data, skipped)
    if "gyro_rad[0]" in d:
        gyro, acc = _vec(d, "gyro_rad"), _vec(d, "accelerometer_m_s2")
        rel = d.get("accelerometer_timestamp_relative")
        valid = np.ones(t.size, bool) if rel is None else rel != RELATIVE_TIMESTAMP_INVALID
    else:           # vehicle_imu: increments over their intervals; its sample time is timestamp_sample
        t = d.get("timestamp_sample", t).astype(np.int64)
        dt_w, dt_a = (d[k].astype(np.float64) * 1e-6 for k in ("delta_angle_dt", "delta_velocity_dt"))
        valid = (dt_w > 0) & (dt_a > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            gyro = [w / dt_w for w in _vec(d, "delta_angle")]
            acc = [v / dt_a for v in _vec(d, "delta_velocity")]
    keep = _drop(valid, "imu_invalid", skipped)
    physical = np.all([np.abs(w) < GYRO_MAX_RADPS for w in gyro] + [np.abs(a) < ACC_MAX_MPS2 for a in acc], axis=0)
    keep &= _drop(physical | ~keep, "imu_out_of_range", skipped)
    m, has_mag = _latest_mag(mag, t, skipped)
    cols = tuple(c[keep] for c in (t, *acc, *gyro, *m, has_mag))
    no_mag = (None, None, None)

    def make(r):
        return ImuSample(r[0], r[1], r[2], r[3], r[4], r[5], r[6], *(r[7:10] if r[10] else no_mag))
    return Stream(data.name, cols, make)


def _latest_mag(mag, t: np.ndarray, skipped) -> tuple[list[np.ndarray], np.ndarray]:
    """For each time in `t`, the latest magnetometer reading (gauss) and whether it is under 0.5 s old."""
    if mag is None:
        return [np.zeros(t.size)] * 3, np.zeros(t.size, bool)
    d, mt = _timed(mag, skipped)
    m = _vec(d, "magnetometer_ga")
    ok = _drop(np.all([np.abs(c) < MAG_MAX_GAUSS for c in m], axis=0), "mag_out_of_range", skipped)
    mt, m = mt[ok], [c[ok] for c in m]
    i = np.searchsorted(mt, t, side="right") - 1
    has = (i >= 0) & (t - mt[np.maximum(i, 0)] < MAG_MAX_AGE_US) if mt.size else np.zeros(t.size, bool)
    i = np.maximum(i, 0)
    return ([c[i] for c in m] if mt.size else [np.zeros(t.size)] * 3), has


def attitude_stream(data, skipped) -> Stream:
    """Attitude (roll, pitch) from vehicle_attitude's quaternion, body FRD to NED."""
    d, t = _timed(data, skipped)
    w, x, y, z = (d[f"q[{i}]"].astype(np.float64) for i in range(4))
    unit = np.abs(w * w + x * x + y * y + z * z - 1.0) < 0.01      # PX4 normalises it: otherwise corrupt bytes
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    ok = _drop(unit & np.isfinite(roll) & np.isfinite(pitch) & (np.abs(pitch) <= 1.5), "attitude_non_finite", skipped)
    return Stream(data.name, (t[ok], roll[ok], pitch[ok]), lambda r: Attitude(r[0], r[1], r[2]))


def vehicle_stream(data, skipped) -> Stream | None:
    """VehicleType at the first vehicle_status and wherever ground-ness changes (None: the log cannot say).

    A ground vehicle is what a MAVLink HEARTBEAT calls one (guard.sources.mavlink): a GROUND_ROVER
    (system_type); without it, PX4's vehicle_type ROVER (which boats share); an old log's
    is_rotary_wing says only "air" when set.
    """
    d, t = _timed(data, skipped)
    if "system_type" in d:
        ground = d["system_type"] == MAV_TYPE_GROUND_ROVER
    elif "vehicle_type" in d:
        ground = d["vehicle_type"] == VEHICLE_TYPE_ROVER
    elif "is_rotary_wing" in d and (d["is_rotary_wing"] != 0).all():
        ground = np.zeros(t.size, bool)
    else:
        return None
    change = np.r_[True, ground[1:] != ground[:-1]] if t.size else np.zeros(0, bool)
    return Stream(data.name, (t[change], ground[change]), lambda r: VehicleType(bool(r[1])))


# -- PX4's own findings ------------------------------------------------------------------------

def episodes(t: np.ndarray, ratio: np.ndarray, test: str) -> list[dict]:
    """One verdict per run of test ratios above 1: its first and last time, and its peak."""
    over = np.isfinite(ratio) & (ratio > 1.0)
    edges = np.flatnonzero(np.diff(np.r_[0, over.astype(np.int8), 0]))
    return [{"time_usec": int(t[a]), "end_usec": int(t[b - 1]), "source": "EKF2", "test": test,
             "peak_ratio": round(float(ratio[a:b].max()), 3)} for a, b in zip(edges[0::2], edges[1::2])]


def ekf_verdicts(ratios, status, skipped) -> list[dict]:
    """Episodes from estimator_innovation_test_ratios (instance 0), else from estimator_status."""
    data, fields = (ratios, RATIO_FIELDS) if ratios is not None else (status, STATUS_FIELDS)
    if data is None:
        return []
    d, t = _timed(data, skipped)
    out = []
    for test, names in fields.items():
        present = [d[n].astype(np.float64) for n in names if n in d]
        if present:
            out += episodes(t, np.fmax.reduce(present), test)
    return out


def message_verdicts(ulog: ULog) -> list[dict]:
    """The autopilot's text messages that mention GPS or GNSS."""
    texts = list(ulog.logged_messages) + [m for ms in ulog.logged_messages_tagged.values() for m in ms]
    return [{"time_usec": int(m.timestamp), "source": "autopilot", "test": "message", "level": m.log_level_str(),
             "text": m.message} for m in texts if GPS_TEXT.search(m.message)]


# -- the reader --------------------------------------------------------------------------------

def rate_hz(t: np.ndarray) -> float:
    """The mean rate of time stamps `t` (us), in Hz (0 for fewer than two)."""
    span = (int(t[-1]) - int(t[0])) / 1e6 if t.size > 1 else 0.0
    return (t.size - 1) / span if span > 0 else 0.0


def _hz(t: np.ndarray) -> str:
    hz = rate_hz(t)
    return f"{hz:.0f} Hz" if hz >= 10 else f"{hz:.1f} Hz"


class UlogReader(LogSource):
    """Samples of a PX4 ULog in time order; `imu=N` reads vehicle_imu instance N instead of
    sensor_combined, `gnss=N` the GNSS receiver N (sensor_gps, or in older logs
    vehicle_gps_position, instance N); `system_id` is accepted for MAVLink's sake and ignored."""

    def __init__(self, path: str, system_id: int = 0, imu: int | None = None, gnss: int | None = None):
        super().__init__()
        self.path = path
        self.rates_hz: dict[str, float] = {}    # each stream read: its mean rate (what `notes` says)
        self.size = os.path.getsize(path) if os.path.isfile(path) else 0
        ulog, cut_at = _load(path)
        self.position = self.size           # pyulog has read the whole file
        self._account(ulog, cut_at)
        sets = {(d.name, d.multi_id): d for d in ulog.data_list if "timestamp" in d.data}
        for (name, _), data in sets.items():
            self.messages[name] += len(data.data["timestamp"])
        self._streams = self._build(sets, imu, gnss)
        self.verdicts = sorted(ekf_verdicts(sets.get(("estimator_innovation_test_ratios", 0)),
                                            sets.get(("estimator_status", 0)), self.skipped)
                               + message_verdicts(ulog), key=lambda v: v["time_usec"])

    def _account(self, ulog: ULog, cut_at: int | None) -> None:
        """What pyulog says it lost, in `skipped`, and what the log is, in `notes`."""
        info = ulog.msg_info_dict
        what = " ".join(str(info[k]) for k in ("sys_name", "ver_hw") if k in info)
        self.notes.append(f"PX4 ULog{': ' + what if what else ''}")
        if ulog.file_corruption:
            self.skipped["ulog_corrupt"] += 1
            self.notes.append("pyulog found corrupt bytes: what it could not parse is lost")
        if cut_at is not None:
            self.skipped["truncated"] += 1
            self.notes.append(f"pyulog stopped at byte {cut_at} of {self.size}: the file is cut inside a "
                              "message, or corrupt bytes read as one long message hide the rest")
        if ulog.dropouts:
            self.skipped["logger_dropouts"] += len(ulog.dropouts)
            ms = sum(d.duration for d in ulog.dropouts)
            self.notes.append(f"the logger dropped data {len(ulog.dropouts)} time(s), {ms} ms in all")
        if ulog.has_data_appended:
            self.notes.append("the log has data appended after the flight (read too)")

    def _build(self, sets: dict, imu: int | None, gnss: int | None) -> list[Stream]:
        """The streams to merge, in the order samples of equal time go out: vehicle, attitude, IMU, GNSS."""
        gps_key = self._pick_gnss(sets, gnss)
        imu_key = ("sensor_combined", 0) if imu is None else ("vehicle_imu", imu)
        if imu is not None and imu_key not in sets:
            raise SourceError(f"{self.path}: no vehicle_imu instance {imu} "
                              f"(instances: {self._instances(sets, 'vehicle_imu') or 'none'})")
        mag = sets.get(("vehicle_magnetometer", 0))
        streams = [self._stream(vehicle_stream, sets.get(("vehicle_status", 0))),
                   self._stream(attitude_stream, sets.get(("vehicle_attitude", 0))),
                   self._stream(imu_stream, sets.get(imu_key), mag),
                   self._stream(gnss_stream, sets.get(gps_key))]
        streams = [s for s in streams if s is not None]
        self._note_streams(sets, streams, imu_key, gps_key)
        if gps_key and gps_key[0] in GPS_TOPICS:
            self.date = self._date(sets[gps_key])
        return streams

    def _stream(self, build, data, *more) -> Stream | None:
        """`build(data, *more, skipped)` in time order; None when the topic is absent or lacks a field."""
        if data is None:
            return None
        try:
            stream = build(data, *more, self.skipped)
        except (KeyError, ValueError) as e:     # a field missing: an unknown version or a corrupt format
            self.notes.append(f"{data.name}: cannot be read ({type(e).__name__}: {e})")
            return None
        if stream is None:
            self.notes.append(f"{data.name}: none of the field layouts guard reads")
            return None
        if not bool(np.all(stream.t_us[1:] >= stream.t_us[:-1])):
            order = np.argsort(stream.t_us, kind="stable")
            stream = Stream(stream.topic, tuple(c[order] for c in stream.columns), stream.make)
        return stream

    def _pick_gnss(self, sets: dict, gnss: int | None) -> tuple[str, int] | None:
        """vehicle_gps_position (what the autopilot uses) by default; receiver N when asked."""
        if gnss is None:
            return next(((t, 0) for t in GPS_TOPICS if (t, 0) in sets), None)
        topic = "sensor_gps" if any(k[0] == "sensor_gps" for k in sets) else "vehicle_gps_position"
        if (topic, gnss) not in sets:
            raise SourceError(f"{self.path}: no GNSS receiver {gnss} "
                              f"({topic} instances: {self._instances(sets, topic) or 'none'})")
        return topic, gnss

    @staticmethod
    def _instances(sets: dict, topic: str) -> str:
        return ", ".join(str(m) for name, m in sorted(sets) if name == topic)

    def _note_streams(self, sets: dict, streams: list[Stream], imu_key, gps_key) -> None:
        used = {("vehicle_status", 0), ("vehicle_attitude", 0), ("vehicle_magnetometer", 0), imu_key, gps_key}
        timed = {s.topic: s.t_us for s in streams if s.t_us.size and s.topic != "vehicle_status"}
        if ("vehicle_magnetometer", 0) in sets:
            timed["vehicle_magnetometer"] = sets["vehicle_magnetometer", 0].data["timestamp"]
        order = (imu_key[0], *GPS_TOPICS, "vehicle_magnetometer", "vehicle_attitude")
        self.rates_hz = {topic: rate_hz(timed[topic]) for topic in order if topic in timed}
        rates = [f"{topic}: {_hz(t)}" for topic, t in ((k, timed[k]) for k in self.rates_hz)]
        self.notes.append("read: " + (", ".join(rates) or "no sensor data"))
        for topic in ("sensor_combined", "vehicle_imu", *GPS_TOPICS, "vehicle_magnetometer"):
            others = [(m, d) for (name, m), d in sorted(sets.items()) if name == topic and (name, m) not in used]
            if others:
                hz = ", ".join(f"{m} ({_hz(d.data['timestamp'])})" for m, d in others)
                self.notes.append(f"not used: {topic} instance(s) {hz}")
        if imu_key == ("sensor_combined", 0) and imu_key in sets:
            self.notes.append("IMU: sensor_combined, the autopilot's selected IMU (imu=N reads vehicle_imu N)")
        if gps_key is None:
            self.notes.append("no GNSS topic (vehicle_gps_position, sensor_gps) in the log")

    def _date(self, data) -> datetime.date | None:
        """The UTC day of the first GNSS record that knows it (time_utc_usec non-zero)."""
        utc = data.data.get("time_utc_usec")
        known = utc[(utc > 946_684_800_000_000) & (utc < 4_102_444_800_000_000)] if utc is not None else []
        if len(known) == 0:
            return None
        return datetime.datetime.fromtimestamp(int(known[0]) / 1e6, datetime.timezone.utc).date()

    def samples(self) -> Iterator[Sample]:
        """The streams merged by time stamp; at equal times in the order of `_build`."""
        streams = self._streams
        if not streams:
            return
        t = np.concatenate([s.t_us for s in streams])
        kind = np.concatenate([np.full(s.t_us.size, k, np.int8) for k, s in enumerate(streams)])
        order = np.lexsort((kind, t))
        t, kind = t[order], kind[order]
        rows = [s.rows() for s in streams]
        makes = [s.make for s in streams]
        for a in range(0, t.size, CHUNK):
            for k, t_us in zip(kind[a:a + CHUNK].tolist(), t[a:a + CHUNK].tolist()):
                sample = makes[k](next(rows[k]))
                if type(sample) is VehicleType:     # no time of its own
                    yield sample
                    continue
                if self.first_time_us is None:
                    self.first_time_us = t_us
                self.last_time_us = t_us
                yield sample
