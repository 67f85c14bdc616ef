"""`DataFlashReader`: the samples of an ArduPilot DataFlash log, in file order.

Units, as ArduPilot logs them, converted here to the samples' SI units:
- time: `TimeUS`, microseconds since boot (older logs: `TimeMS` ms; their GPS has boot ms in `T` and
  GPS time of week in `TimeMS`/`Week`). All samples are on this one time base.
- IMU (IMU, IMU2.. or an instance column `I`): GyrX..Z rad/s, AccX..Z m/s^2 specific force (about
  -9.8 on z at rest), body frame x forward, y right, z down (FRD), corrected and rotated to the body.
- MAG: MagX..Z milligauss (int16), body frame, offsets applied. All zero: no compass. Each reading
  rides on the first IMU sample after it, if that is fresh (`guard.sources.logs_common.mag_fresh`),
  and on no other: a 10 Hz compass among 50 Hz IMU samples is 10 measurements a second, not 50 (the
  same error counted five times over, which a CUSUM sums into alarms).
- GPS: Status (AP_GPS::GPS_Status, 3 = 3D fix and better), Lat/Lng degE7, Alt cm, Spd m/s, GCrs deg
  (ground course), VZ m/s, HDop (stored x 100, 'c'). GPA (written with the same TimeUS): HAcc m and
  SAcc m/s, stored in cm ('C').
- ATT: Roll, Pitch in centidegrees ('c'); a roll beyond 180 degrees or a pitch beyond 1.5 rad is corrupt.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import struct
from collections.abc import Iterator
from itertools import repeat

from guard.errors import SourceError
from guard.model.samples import Attitude, GnssFix, ImuSample, Sample, VehicleType
from guard.sources.base import LogSource
import guard.sources.dataflash.survey as survey
from guard.sources.dataflash.index import MAX_BOOT_US, Log, one_line, open_index
from guard.sources.dataflash.verdicts import autopilot_verdicts
from guard.sources.logs_common import mag_fresh

MAX_ACC_MPS2, MAX_GYRO_RADPS = 2000.0, 200.0     # beyond any MEMS range: corrupt data
MAX_SPEED_MPS = 600.0             # beyond a GNSS receiver's export limit: corrupt data
MAX_MAG_MGAUSS = 32_767           # MAG's int16: more comes only from a corrupt format


class DataFlashReader(LogSource):
    """Samples of an ArduPilot DataFlash log: GPS, IMU (+ the latest MAG), ATT and the vehicle type.

    `imu` and `gnss` pick an instance (default 0, the primary); `system_id` is accepted and ignored
    (a DataFlash log holds one vehicle); `as_logged` keeps the autopilot's time stamps even where its
    clock parts from the GNSS time (survey.clock_rate). Opening surveys the log: rates, other instances, the date,
    the vehicle and the autopilot's own verdicts; `samples()` then decodes the streams in file order.
    """

    def __init__(self, path: str, system_id: int = 0, imu: int | None = None, gnss: int | None = None,
                 as_logged: bool = False):
        super().__init__()
        self.path = path
        self._index = open_index(path)
        self._log = Log(self._index)
        self.size, self.position = self._index.data_len, 0
        self.ground: bool | None = None         # the vehicle class, from the firmware string
        self._mag_now: tuple | None = None      # the latest MAG reading: (t_us, x, y, z gauss)
        try:
            self._survey(imu, gnss, as_logged)
        except SourceError:
            self.close()
            raise
        except Exception as e:      # noqa: BLE001 - a format too damaged to survey: one line for the user
            self.close()
            raise SourceError(f"{path}: DataFlash log not readable: {one_line(e)}") from None

    def close(self) -> None:
        self._index.close()

    def _survey(self, imu: int | None, gnss: int | None, as_logged: bool = False) -> None:
        idx, lg = self._index, self._log
        self.messages.update({idx.formats[t].name: len(offs) for t, offs in enumerate(idx.offsets)
                              if offs and t in idx.formats})
        survey.account(idx, self.skipped, self.notes)
        self.ground = survey.vehicle(lg, self.notes)
        self._imu_n, self._imu = survey.choose(lg, "IMU", imu, "--imu", self.path, self.notes)
        self._gnss_n, self._gnss = survey.choose(lg, "GPS", gnss, "--gnss", self.path, self.notes)
        self._mag = lg.instances("MAG").get(0)
        self._att = ("ATT", lg.offsets("ATT")) if lg.offsets("ATT") else None
        self._accuracy = survey.accuracies(lg, self._gnss, self._gnss_n, self.notes)
        self.date, self.utc_offset_us = survey.gps_utc(lg, self._gnss)
        # (t0, rate) or None: as logged (`as_logged`: the time stamps as the autopilot wrote them, always)
        self.clock = None if as_logged else survey.clock_rate(lg, self._gnss, self.notes)
        used = [(f"IMU {self._imu_n}", self._imu), (f"GPS {self._gnss_n}", self._gnss), ("MAG", self._mag),
                ("ATT", self._att)]
        rates = [f"{label}: {survey.rate(lg, s)} Hz" for label, s in used if s is not None]
        if rates:
            self.notes.insert(0, ", ".join(rates))
        self.verdicts = autopilot_verdicts(lg, self.notes)
        self._verdicts_on_clock()

    # -- samples -----------------------------------------------------------------------------------
    def samples(self) -> Iterator[Sample]:
        if self.ground is not None:     # the whole log's vehicle, before its first sample
            yield VehicleType(self.ground)
        self._mag_now = None
        streams = [(s, convert, cols) for s, convert, cols in (
            (self._gnss, self._gnss_sample, ["Status", "Lat", "Lng", "Alt", "Spd", "GCrs", "HDop"]),
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
            if self.clock is not None:      # on the GNSS receiver's clock (survey.clock_rate)
                sample = dataclasses.replace(sample, t_us=self.on_clock(sample.t_us))
            backwards += sample.t_us < last - 1000
            last = sample.t_us
            self.first_time_us = sample.t_us if self.first_time_us is None else self.first_time_us
            self.last_time_us = sample.t_us
            yield sample
        self.position = self.size
        if backwards:
            self.notes.append(f"{backwards} samples earlier than the one before them (file order kept)")

    def _gnss_sample(self, v: tuple) -> tuple[GnssFix | None, str | None]:
        t, status, lat, lon, alt, speed, course, hdop = v
        if not (0 <= status <= 8 and math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)):
            return None, "bad_message"      # (None, a column a corrupt format lacks: TypeError, bad_message too)
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
        hdop = hdop if isinstance(hdop, int | float) and 0.0 < hdop < 50.0 else None   # else unknown or corrupt
        return GnssFix(int(t), fix, lat, lon, alt, vn, ve, h_acc, vel_acc, hdop), None

    def _imu_sample(self, v: tuple) -> tuple[ImuSample | None, str | None]:
        t, ax, ay, az, gx, gy, gz = v
        a, w = MAX_ACC_MPS2, MAX_GYRO_RADPS
        if not (abs(ax) <= a and abs(ay) <= a and abs(az) <= a and abs(gx) <= w and abs(gy) <= w and abs(gz) <= w):
            return None, "bad_message"      # also NaN: every comparison with NaN is False
        mag = self._mag_now
        if mag is None or not mag_fresh(t, mag[0]):
            return ImuSample(int(t), ax, ay, az, gx, gy, gz, None, None, None), None
        self._mag_now = None            # one reading, one measurement: it rides on the first IMU sample only
        return ImuSample(int(t), ax, ay, az, gx, gy, gz, mag[1], mag[2], mag[3]), None

    def _mag_reading(self, v: tuple) -> tuple[None, str | None]:
        t, mx, my, mz = v
        if not all(abs(m) <= MAX_MAG_MGAUSS for m in (mx, my, mz)):     # also NaN: a corrupt format
            return None, "bad_message"
        self._mag_now = None if (mx, my, mz) == (0, 0, 0) else (t, mx / 1000.0, my / 1000.0, mz / 1000.0)
        return None, None

    def _attitude(self, v: tuple) -> tuple[Attitude | None, str | None]:
        t, roll, pitch = v
        if roll is None or pitch is None:
            return None, "bad_message"
        roll, pitch = math.radians(roll), math.radians(pitch)
        if not (abs(roll) <= math.pi and abs(pitch) <= 1.5):     # int16 centidegrees reach 327.67: corrupt
            return None, "attitude_non_finite"
        return Attitude(int(t), roll, pitch), None
