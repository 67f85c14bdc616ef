"""What a ULog is and what reading it found: the notes for the user, the topics' rates and the date.

Rates in Hz, from `timestamp` (microseconds since boot). The date from the GNSS topic's
time_utc_usec: UTC microseconds since 1970, 0 before the receiver knows it.
"""

from __future__ import annotations

import datetime

import numpy as np
from pyulog import ULog

from guard.sources.clock import gnss_time_clock
from guard.sources.ulog.framing import Walk
from guard.sources.ulog.load import GPS_TOPICS


def rate_hz(t: np.ndarray) -> float:
    """The mean rate of time stamps `t` (us), in Hz (0 for fewer than two)."""
    span = (int(t[-1]) - int(t[0])) / 1e6 if t.size > 1 else 0.0
    return (t.size - 1) / span if span > 0 else 0.0


def _hz(t: np.ndarray) -> str:
    hz = rate_hz(t)
    return f"{hz:.0f} Hz" if hz >= 10 else f"{hz:.1f} Hz"


def account(ulog: ULog, cut_at: int | None, walk: Walk, size: int, skipped, notes: list[str]) -> None:
    """What the framing's walk skipped and pyulog says it lost, in `skipped`, and what the log is, in
    `notes`."""
    info = ulog.msg_info_dict
    what = " ".join(str(info[k]) for k in ("sys_name", "ver_hw") if k in info)
    notes.append(f"PX4 ULog{': ' + what if what else ''}")
    if walk.spans:
        skipped["garbage_bytes"] += walk.skipped_bytes
        first = walk.spans[0][0]
        notes.append(f"{len(walk.spans)} corrupt span(s) of the file, {walk.skipped_bytes} bytes (the first at byte "
                     f"{first}), could not be framed as messages: skipped, the messages after them read")
    if ulog.file_corruption:
        skipped["ulog_corrupt"] += 1
        notes.append("pyulog found corrupt bytes: what it could not parse is lost")
    if cut_at is not None:
        skipped["truncated"] += 1
        notes.append(f"pyulog stopped at byte {cut_at} of {size}: the file is cut inside a "
                     "message, or corrupt bytes read as one long message hide the rest")
    if ulog.dropouts:
        skipped["logger_dropouts"] += len(ulog.dropouts)
        ms = sum(d.duration for d in ulog.dropouts)
        notes.append(f"the logger dropped data {len(ulog.dropouts)} time(s), {ms} ms in all")
    if ulog.has_data_appended:
        notes.append("the log has data appended after the flight (read too)")


def instances(sets: dict, topic: str) -> str:
    """The instance numbers of a topic in the log, as a list for the user."""
    return ", ".join(str(m) for name, m in sorted(sets) if name == topic)


def note_streams(sets: dict, streams: list, imu_key, gps_key, notes: list[str]) -> dict[str, float]:
    """The rate (Hz) of each topic read, noted with the instances not used; returns the rates."""
    used = {("vehicle_status", 0), ("vehicle_attitude", 0), ("vehicle_magnetometer", 0), imu_key, gps_key}
    timed = {s.topic: s.t_us for s in streams if s.t_us.size and s.topic != "vehicle_status"}
    if ("vehicle_magnetometer", 0) in sets:
        timed["vehicle_magnetometer"] = sets["vehicle_magnetometer", 0].data["timestamp"]
    order = (imu_key[0], *GPS_TOPICS, "vehicle_magnetometer", "vehicle_attitude")
    rates_hz = {topic: rate_hz(timed[topic]) for topic in order if topic in timed}
    rates = [f"{topic}: {_hz(t)}" for topic, t in ((k, timed[k]) for k in rates_hz)]
    notes.append("read: " + (", ".join(rates) or "no sensor data"))
    for topic in ("sensor_combined", "vehicle_imu", *GPS_TOPICS, "vehicle_magnetometer"):
        others = [(m, d) for (name, m), d in sorted(sets.items()) if name == topic and (name, m) not in used]
        if others:
            hz = ", ".join(f"{m} ({_hz(d.data['timestamp'])})" for m, d in others)
            notes.append(f"not used: {topic} instance(s) {hz}")
    if imu_key == ("sensor_combined", 0) and imu_key in sets:
        notes.append("IMU: sensor_combined, the autopilot's selected IMU (imu=N reads vehicle_imu N)")
    if gps_key is None:
        notes.append("no GNSS topic (vehicle_gps_position, sensor_gps) in the log")
    return rates_hz


def utc_date(data) -> tuple[datetime.date | None, int | None]:
    """The UTC day of the first GNSS record that knows it (time_utc_usec non-zero), and the offset
    that turns the log's timestamps into UTC microseconds there (None, None: the log does not say)."""
    utc = data.data.get("time_utc_usec")
    if utc is None:
        return None, None
    known = (utc > 946_684_800_000_000) & (utc < 4_102_444_800_000_000)
    if not known.any():
        return None, None
    i = int(known.argmax())
    first = int(utc[i])
    return (datetime.datetime.fromtimestamp(first / 1e6, datetime.timezone.utc).date(),
            first - int(data.data["timestamp"][i]))


def gnss_clock(data, notes: list[str]) -> tuple[int, float] | None:
    """(t0, rate) of the log's boot clock against the GNSS receiver's UTC (time_utc_usec), where the
    two part in a straight line (guard.sources.clock.gnss_time_clock, as a DataFlash log's GNSS time
    is checked); None: as logged."""
    utc = data.data.get("time_utc_usec")
    if utc is None:
        return None
    t = data.data["timestamp"]
    known = (utc > 946_684_800_000_000) & (utc < 4_102_444_800_000_000)
    if "fix_type" in data.data:
        known &= data.data["fix_type"] >= 3
    return gnss_time_clock((t[known] / 1e6).tolist(), (utc[known] / 1e6).tolist(), notes)
