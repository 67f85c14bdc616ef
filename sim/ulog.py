"""PX4 ULog (.ulg) output of the simulator: its MAVLink messages as the topics a PX4 log holds.

Topics (field names, units and frames of PX4's msg/*.msg):
- `sensor_gps` (the newer layout): latitude_deg/longitude_deg (float64, from GPS_RAW_INT's degE7),
  altitude_msl_m, vel_n_m_s/vel_e_m_s (float32, from its speed and course over ground), eph m and
  s_variance_m_s m/s (1-sigma, from h_acc and vel_acc; -1 when unknown), hdop/vdop (its eph/epv DOP x 100),
  fix_type, time_utc_usec = guard_sim.mavout.TLOG_EPOCH_US + time (the day a tlog of the same run says).
- `sensor_combined`: gyro_rad rad/s and accelerometer_m_s2 m/s^2 (float32, from RAW_IMU's mrad/s and
  mG), body FRD; `vehicle_magnetometer`: magnetometer_ga gauss (from its mGauss), when it has one.
- `vehicle_status`: at every autopilot HEARTBEAT, system_type = its MAV_TYPE, and PX4's
  vehicle_type (3 rover for a ground rover or a boat, 2 fixed wing, 1 rotary wing, 0 unknown).

Time base: each record's `timestamp` is the simulator's time in microseconds, the time since boot
of a PX4 log (a vehicle booted at the start of the run), the same number as the tlog's time_usec.

Written with pyulog's own writer (`ULog.write_ulog`): pyulog has no public way to build a log, so
the writer fills a ULog object the way its parser does (format messages, one subscription per
topic, each topic's records as one numpy buffer); `tests/integration/test_ulog.py` reads it back.
pyulog writes no sync messages; the writer adds one a second (a PX4 log has them every so often),
so that a reader can resynchronise after corrupt bytes. The messages are kept in memory until `close()`.
"""

from __future__ import annotations

import io
import math
import struct

import numpy as np
from pyulog import ULog

from .mavout import TLOG_EPOCH_US, mavlink
from .sensors import G

UNKNOWN_U16 = 65535
SYNC = struct.pack("<HB", len(ULog.SYNC_BYTES), ord("S")) + ULog.SYNC_BYTES
SYNC_EVERY_US = 1_000_000
DEVICE_ID = 0x00A0_0001                     # any constant: one simulated receiver, one IMU, one compass

# topic -> fields (type, array size, name), 8-byte fields first, as PX4 lays its messages out
FORMATS = {
    "sensor_combined": [("uint64_t", 0, "timestamp"), ("float", 3, "gyro_rad"), ("uint32_t", 0, "gyro_integral_dt"),
                        ("int32_t", 0, "accelerometer_timestamp_relative"), ("float", 3, "accelerometer_m_s2"),
                        ("uint32_t", 0, "accelerometer_integral_dt"), ("uint8_t", 0, "accelerometer_clipping"),
                        ("uint8_t", 0, "gyro_clipping"), ("uint8_t", 0, "accel_calibration_count"),
                        ("uint8_t", 0, "gyro_calibration_count")],
    "vehicle_magnetometer": [("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"),
                             ("uint32_t", 0, "device_id"), ("float", 3, "magnetometer_ga"),
                             ("uint8_t", 0, "calibration_count")],
    "sensor_gps": [("uint64_t", 0, "timestamp"), ("uint64_t", 0, "timestamp_sample"),
                   ("double", 0, "latitude_deg"), ("double", 0, "longitude_deg"), ("double", 0, "altitude_msl_m"),
                   ("double", 0, "altitude_ellipsoid_m"), ("uint64_t", 0, "time_utc_usec"),
                   ("uint32_t", 0, "device_id"), ("float", 0, "s_variance_m_s"), ("float", 0, "c_variance_rad"),
                   ("float", 0, "eph"), ("float", 0, "epv"), ("float", 0, "hdop"), ("float", 0, "vdop"),
                   ("float", 0, "vel_m_s"), ("float", 0, "vel_n_m_s"), ("float", 0, "vel_e_m_s"),
                   ("float", 0, "vel_d_m_s"), ("float", 0, "cog_rad"), ("int32_t", 0, "timestamp_time_relative"),
                   ("float", 0, "heading"), ("uint8_t", 0, "fix_type"), ("bool", 0, "vel_ned_valid"),
                   ("uint8_t", 0, "satellites_used")],
    "vehicle_status": [("uint64_t", 0, "timestamp"), ("uint8_t", 0, "arming_state"), ("uint8_t", 0, "system_type"),
                       ("uint8_t", 0, "vehicle_type"), ("bool", 0, "is_vtol")],
}
# MAVLink MAV_TYPE -> PX4's vehicle_status.vehicle_type (PX4 flies boats as rovers)
VEHICLE_TYPE = {mavlink.MAV_TYPE_GROUND_ROVER: 3, mavlink.MAV_TYPE_SURFACE_BOAT: 3, mavlink.MAV_TYPE_FIXED_WING: 2,
                mavlink.MAV_TYPE_QUADROTOR: 1, mavlink.MAV_TYPE_HEXAROTOR: 1, mavlink.MAV_TYPE_OCTOROTOR: 1,
                mavlink.MAV_TYPE_TRICOPTER: 1, mavlink.MAV_TYPE_HELICOPTER: 1, mavlink.MAV_TYPE_COAXIAL: 1,
                mavlink.MAV_TYPE_AIRSHIP: 4}


class UlogWriter:
    """Collects the simulator's messages, send(t_us, msg), and writes a .ulg at close()."""

    def __init__(self, path: str):
        self.path = path
        self.rows: dict[str, list[tuple]] = {topic: [] for topic in FORMATS}
        self._last_imu_us: int | None = None

    def send(self, t_us: int, msg) -> None:
        name = msg.get_type()
        if name == "RAW_IMU":
            self._imu(t_us, msg)
        elif name == "GPS_RAW_INT":
            self.rows["sensor_gps"].append(gps_row(t_us, msg))
        elif name == "HEARTBEAT" and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
            armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.rows["vehicle_status"].append((t_us, 2 if armed else 1, msg.type, VEHICLE_TYPE.get(msg.type, 0), 0))

    def _imu(self, t_us: int, msg) -> None:
        """RAW_IMU (mG, mrad/s, mGauss) as sensor_combined and vehicle_magnetometer (SI, gauss)."""
        a, w = G / 1000.0, 1e-3
        dt = t_us - self._last_imu_us if self._last_imu_us is not None else 0
        self._last_imu_us = t_us
        self.rows["sensor_combined"].append((t_us, msg.xgyro * w, msg.ygyro * w, msg.zgyro * w, dt, 0,
                                             msg.xacc * a, msg.yacc * a, msg.zacc * a, dt, 0, 0, 0, 0))
        mag = (msg.xmag, msg.ymag, msg.zmag)
        # (0, 0, 0): RAW_IMU's way of saying "no magnetometer"; a held reading is written once (Encoder.raw_imu)
        if mag != (0, 0, 0) and not getattr(msg, "mag_held", False):
            self.rows["vehicle_magnetometer"].append((t_us, t_us, DEVICE_ID, *(m / 1000.0 for m in mag), 0))

    def close(self) -> None:
        buf = io.BytesIO()
        to_ulog(self.rows).write_ulog(buf)
        with open(self.path, "wb") as f:
            f.write(with_syncs(buf.getvalue()))


def gps_row(t_us: int, msg) -> tuple:
    """GPS_RAW_INT (degE7, mm, cm/s, cdeg, DOP x 100, accuracies in mm and mm/s) as a sensor_gps record."""
    vel_known = msg.vel != UNKNOWN_U16 and msg.cog != UNKNOWN_U16
    speed, cog = (msg.vel / 100.0, math.radians(msg.cog / 100.0)) if vel_known else (0.0, 0.0)
    alt = msg.alt / 1000.0
    return (t_us, t_us, msg.lat * 1e-7, msg.lon * 1e-7, alt, getattr(msg, "alt_ellipsoid", msg.alt) / 1000.0,
            TLOG_EPOCH_US + t_us, DEVICE_ID, _accuracy(getattr(msg, "vel_acc", 0)), 0.0,
            _accuracy(getattr(msg, "h_acc", 0)), _accuracy(getattr(msg, "v_acc", 0)), msg.eph / 100.0, msg.epv / 100.0,
            speed, speed * math.cos(cog), speed * math.sin(cog), 0.0, math.remainder(cog, math.tau), 0,
            math.nan, msg.fix_type, vel_known, msg.satellites_visible)


def _accuracy(mm: int) -> float:
    """A GPS_RAW_INT accuracy (mm or mm/s; 0: unknown) as sensor_gps's eph/epv/s_variance_m_s (m, m/s).

    Unknown is -1 in sensor_gps, as PX4's DroneCAN GNSS driver (UavcanGnssBridge) writes eph, epv and
    s_variance_m_s when the receiver sends no covariance (c_variance_rad, never known here, stays 0).
    """
    return mm / 1000.0 if mm > 0 else -1.0


def with_syncs(data: bytes) -> bytes:
    """`data`, a ULog as pyulog writes it, with a sync message before the first data message of each
    second, as PX4's logger writes them every so often: a reader that meets corrupt bytes can look
    for the next one (pyulog's writer writes none)."""
    out, pos, next_us = bytearray(data[:16]), 16, 0
    while pos + 3 <= len(data):
        size, kind = struct.unpack_from("<HB", data, pos)
        if kind == ord("D"):
            (t_us,) = struct.unpack_from("<Q", data, pos + 5)     # after msg_id: every topic here starts with it
            if t_us >= next_us:
                out += SYNC
                next_us = (t_us // SYNC_EVERY_US + 1) * SYNC_EVERY_US
        out += data[pos:pos + 3 + size]
        pos += 3 + size
    return bytes(out)


def to_ulog(rows: dict[str, list[tuple]], formats: dict = FORMATS) -> ULog:
    """A pyulog ULog holding `rows` (topic -> records in the flattened field order of `formats`)."""
    ulog = ULog(None)
    ulog._file_version = 1
    ulog._start_timestamp = min((r[0][0] for r in rows.values() if r), default=0)
    ulog._msg_info_dict["sys_name"] = "guard sim"
    ulog._msg_info_dict_types["sys_name"] = "char[9]"
    for topic, fields in formats.items():
        text = topic + ":" + "".join(f"{t}[{n}] {name};" if n else f"{t} {name};" for t, n, name in fields)
        ulog._message_formats[topic] = ULog.MessageFormat(text.encode(), None)
    for msg_id, (topic, records) in enumerate((t, r) for t, r in rows.items() if r):
        subscription = ULog._MessageAddLogged(struct.pack("<BH", 0, msg_id) + topic.encode(), None,
                                              ulog._message_formats)
        subscription.buffer = bytearray(np.array(records, dtype=subscription.dtype).tobytes())
        ulog._data_list.append(ULog.Data(subscription))
    return ulog
