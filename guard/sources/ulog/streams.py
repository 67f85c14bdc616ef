"""Each ULog topic guard reads, as columns of checked records and the samples made from them.

Time base: every record's `timestamp`, microseconds since the autopilot booted (PX4's hrt). Units
and frames, from PX4's msg definitions (msg/*.msg):
- `vehicle_gps_position` / `sensor_gps` (GNSS): older layout lat/lon int32 degE7 and alt int32 mm
  (MSL); newer layout latitude_deg/longitude_deg float64 and altitude_msl_m; told apart by their field
  names. vel_n_m_s, vel_e_m_s m/s; fix_type >= 3 is a 3D fix; eph is the receiver's horizontal
  accuracy in metres (u-blox hAcc, not a DOP); s_variance_m_s is, despite its name, a 1-sigma speed
  accuracy in m/s (u-blox sAcc; EKF2 squares it).
- `sensor_combined` (IMU the autopilot selected): gyro_rad rad/s, accelerometer_m_s2 specific force
  m/s^2 (about -9.8 on z at rest), body FRD; `timestamp` is the gyro's sample time, the
  accelerometer's is timestamp + accelerometer_timestamp_relative (0x7fffffff: no valid sample).
  `vehicle_imu` instance N (imu=N): delta_angle rad and delta_velocity m/s over delta_*_dt us.
- `vehicle_magnetometer`: magnetometer_ga, gauss, body FRD; each reading attached to the first IMU
  sample after it, when under 0.5 s old (`guard.sources.logs_common.mag_fresh`), and to no other.
- `vehicle_attitude`: q = (w, x, y, z), rotation from body FRD to NED: roll and pitch in radians.
- `vehicle_status`: system_type (the MAVLink MAV_TYPE of its HEARTBEAT) or vehicle_type (1 rotary
  wing, 2 fixed wing, 3 rover, 4 airship) or, in old logs, is_rotary_wing.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from guard.model.samples import Attitude, GnssFix, ImuSample, Sample, VehicleType
from guard.sources.logs_common import mag_fresh

MAX_BOOT_TIME_US = 30 * 86_400_000_000      # a time stamp past 30 days of uptime is corrupt bytes
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
GYRO_MAX_RADPS, ACC_MAX_MPS2, MAG_MAX_GAUSS = 100.0, 1000.0, 10.0   # beyond any MEMS sensor's range
SPEED_MAX_MPS, ACCURACY_MAX = 600.0, 1e4    # beyond a GNSS receiver's limits (m/s; m and m/s)
MAV_TYPE_GROUND_ROVER, VEHICLE_TYPE_ROVER = 10, 3
CHUNK = 4096


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


def timed(data, skipped) -> tuple[dict[str, np.ndarray], np.ndarray]:
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
    d, t = timed(data, skipped)
    if "latitude_deg" in d:
        lat, lon, alt = (d[k].astype(np.float64) for k in ("latitude_deg", "longitude_deg", "altitude_msl_m"))
    elif "lat" in d:
        lat, lon = d["lat"] * 1e-7, d["lon"] * 1e-7
        alt = d["alt"] / 1000.0
    else:
        return None
    nan = np.full(t.size, np.nan)
    fix_ok = d["fix_type"] >= 3
    # without a fix the position means nothing (the core does not read it): where it is not finite, 0
    lat, lon, alt = (np.where(fix_ok | np.isfinite(v), v, 0.0) for v in (lat, lon, alt))
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
    d, t = timed(data, skipped)
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
    """For each time in `t`, the latest magnetometer reading (gauss) and whether it is fresh."""
    if mag is None:
        return [np.zeros(t.size)] * 3, np.zeros(t.size, bool)
    d, mt = timed(mag, skipped)
    m = _vec(d, "magnetometer_ga")
    ok = _drop(np.all([np.abs(c) < MAG_MAX_GAUSS for c in m], axis=0), "mag_out_of_range", skipped)
    mt, m = mt[ok], [c[ok] for c in m]
    i = np.searchsorted(mt, t, side="right") - 1
    has = (i >= 0) & mag_fresh(t, mt[np.maximum(i, 0)]) if mt.size else np.zeros(t.size, bool)
    # one reading, one measurement: on the first IMU sample after it only (a 2 Hz magnetometer among
    # 220 IMU samples a second is 2 measurements a second, not 220)
    has &= np.concatenate(([True], i[1:] != i[:-1])) if t.size else has
    i = np.maximum(i, 0)
    return ([c[i] for c in m] if mt.size else [np.zeros(t.size)] * 3), has


def attitude_stream(data, skipped) -> Stream:
    """Attitude (roll, pitch) from vehicle_attitude's quaternion, body FRD to NED."""
    d, t = timed(data, skipped)
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
    d, t = timed(data, skipped)
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
