"""What opening a DataFlash log finds, before any sample is read: what DFReader could not frame,
the vehicle, the sensor instances and their rates, GPA's accuracies and the day the log was recorded.

Units, as ArduPilot logs them: GPS Status (AP_GPS::GPS_Status, 3 = 3D fix and better), GWk/GMS GPS
week and ms of week (older logs Week/TimeMS); GPA (written with the same TimeUS as its GPS): HAcc m
and SAcc m/s, stored in cm ('C'). Rates in Hz, from boot time stamps in microseconds.
"""

from __future__ import annotations

import datetime
import math
import re
import statistics

from guard.errors import SourceError
from guard.sources.clock import gnss_time_clock
from guard.sources.dataflash.index import HEAD, Log

GPS_EPOCH = datetime.datetime(1980, 1, 6, tzinfo=datetime.timezone.utc)
LEAP_SECONDS = 18
FIRMWARE = re.compile(r"^(?:Ardu|APM:?)\s*(Rover|Copter|Plane|Sub|Heli|Blimp)", re.IGNORECASE)
BUILD_GROUND = {1: True, 2: False, 3: False, 7: False, 12: False, 13: False}   # VER.BU: Rover, Copter, ...


def _rate_hz(times: list[int]) -> float | None:
    """A stream's rate from the median interval between its messages (robust to gaps and bursts)."""
    steps = [b - a for a, b in zip(times, times[1:]) if b > a]
    return round(1e6 / statistics.median(steps), 1) if steps else None


def rate(log: Log, stream: tuple[str, list[int]]) -> float | None:
    """The rate (Hz) of a stream (type name, offsets)."""
    return _rate_hz(log.times(*stream))


def account(index, skipped, notes: list[str]) -> None:
    """Count what DFReader could not frame: a cut last message, garbage, headers of an undeclared type,
    a tail it did not read."""
    size = index.data_len
    spans, stop = 0, 0
    for t, offs in enumerate(index.offsets):
        if offs and t not in index.formats:         # headers of a type no FMT declared, stepped past
            skipped["undeclared_type"] += len(offs)
            spans += 3 * len(offs)
            stop = max(stop, offs[-1] + 3)
            continue
        if not offs:
            continue
        length = index.formats[t].len
        spans += length * len(offs)
        if offs[-1] + length > size:        # the last message, cut: only its first bytes are there
            skipped["truncated"] += 1
            spans -= offs[-1] + length - size
        stop = max(stop, offs[-1] + length)
    garbage = min(stop, size) - spans
    if garbage > 0:
        skipped["garbage_bytes"] += garbage
    if index.formats.refused:
        skipped["bad_format"] += index.formats.refused
    if index.early:
        skipped["undeclared_type"] += index.early
    tail, data = size - stop, index.data_map
    fmt = index.formats.get(data[stop + 2]) if tail >= 3 and data[stop:stop + 2] == HEAD else None
    if 0 < tail < 3 and HEAD.startswith(data[stop:size]) or fmt is not None and tail < fmt.len:
        skipped["truncated"] += 1           # the last message, cut in its header or right after it
    elif tail >= 3 and data[stop:stop + 2] == HEAD:
        skipped["unread_bytes"] += tail
        notes.append(f"reading stopped at byte {stop} of {size} (corrupt data DFReader could not frame); "
                     f"the last {tail} bytes are not read")
    elif tail > 0:
        skipped["garbage_bytes"] += tail


def vehicle(log: Log, notes: list[str]) -> bool | None:
    """Ground vehicle or not, from the firmware string (MSG) or the build type (VER.BU)."""
    for _, text in log.texts("MSG", "Message"):
        if m := FIRMWARE.match(text):
            ground = m.group(1).lower() == "rover"
            notes.append(f"autopilot: {text}")
            return ground
    if log.format("VER") is not None and "BU" in log.format("VER").colhash:
        for _, build in log.rows("VER", ["BU"]):
            return BUILD_GROUND.get(build)
    return None


def choose(log: Log, base: str, wanted: int | None, option: str, path: str,
           notes: list[str]) -> tuple[int | None, tuple | None]:
    """The instance wanted (default: the primary) and its stream (type name, offsets); a note on
    the others."""
    found = log.instances(base)
    n = min(found, default=None) if wanted is None else wanted
    if wanted is not None and wanted not in found:
        have = ", ".join(str(i) for i in sorted(found)) or "none"
        raise SourceError(f"{path}: no {base} {wanted} in this log ({base} instances: {have})")
    if n is None:
        notes.append(f"no {base} messages in this log")
        return None, None
    for i in sorted(set(found) - {n}):
        notes.append(f"also {base} {i} at {rate(log, found[i])} Hz, not used: {option} {i} to replay it")
    return n, found[n]


def accuracies(log: Log, gnss: tuple | None, n: int | None,
               notes: list[str]) -> dict[int, tuple[float | None, float | None]]:
    """GPA's horizontal and speed accuracy (m, m/s) by time stamp, for the GPS instance used, `n`
    (ArduPilot writes GPS and GPA with one time stamp). An older log's UBX3 rows (ArduPilot 3.2 and
    3.3 on a u-blox: hAcc, sAcc, stamped apart from its GPS rows) are not read, and that is said: the
    fixes are taken as a receiver's that reports none (README, "The receiver's own accuracy": read,
    they traded detections for alarms, and were no truer a model)."""
    if gnss is None:
        return {}
    gpa = log.instances("GPA").get(n)
    if gpa is None:
        if log.offsets("UBX3"):
            notes.append("the receiver's accuracy logged in UBX3 rows (hAcc, sAcc) is not read: its fixes are "
                         "tested as a receiver's that reports none (README)")
        return {}
    def known(a) -> float | None:       # 0: not known; not a positive finite number: a corrupt format
        return a if isinstance(a, int | float) and 0 < a < math.inf else None
    return {t: (known(h), known(s)) for t, h, s in log.rows(gpa[0], ["HAcc", "SAcc"], gpa[1])}


def gps_utc(log: Log, gnss: tuple | None) -> tuple[datetime.date | None, int | None]:
    """The UTC day of the first GPS message with a fix (GWk/GMS; older logs Week/TimeMS), and the
    offset that turns the log's TimeUS into UTC microseconds there (None, None: the log does not say)."""
    if gnss is None:
        return None, None
    name, offs = gnss
    cols = log.format(name).colhash
    week, ms = ("GWk", "GMS") if "GWk" in cols else ("Week", "TimeMS") if "Week" in cols else (None, None)
    if week is None:
        return None, None
    for t_us, status, wk, wms in log.rows(name, ["Status", week, ms], offs):
        if status is not None and wk is not None and wms is not None and status >= 3 and 0 < wk < 10_000:
            utc = GPS_EPOCH + datetime.timedelta(weeks=wk, milliseconds=wms) - datetime.timedelta(seconds=LEAP_SECONDS)
            return utc.date(), round(utc.timestamp() * 1e6) - int(t_us)
    return None, None


def clock_rate(log: Log, gnss: tuple | None, notes: list[str]) -> tuple[int, float] | None:
    """(t0, rate): the autopilot's boot clock against the GNSS receiver's own (GPS week and ms, which
    every fix carries), fitted as a line over the whole log. A real autopilot's clock keeps time to
    50 ppm; some do not (a 2014 Linux autopilot's ran 8 % slow: every interval it stamped, the IMU's
    included, 8 % short, so its integrated speed, heading and position ran 8 % behind the receiver's).
    When the two part by more than CLOCK_TOLERANCE in a straight line, the reader scales its time
    stamps by `rate` about t0 (the first fix's boot time) and says so; a GNSS time that jumps (a
    receiver restarting, or a spoofer moving it) is not a line, and corrects nothing
    (guard.sources.clock.gnss_time_clock, which a ULog's GNSS time goes through too)."""
    if gnss is None:
        return None
    name, offs = gnss
    cols = log.format(name).colhash
    week, ms = ("GWk", "GMS") if "GWk" in cols else ("Week", "TimeMS") if "Week" in cols else (None, None)
    if week is None:
        return None
    boot, gps = [], []
    for t_us, status, wk, wms in log.rows(name, ["Status", week, ms], offs):
        if status is not None and wk is not None and wms is not None and status >= 3 and 0 < wk < 10_000:
            boot.append(t_us / 1e6)
            gps.append(wk * 604_800.0 + wms / 1e3)
    return gnss_time_clock(boot, gps, notes)
