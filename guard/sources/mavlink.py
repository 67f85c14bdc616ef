"""The MAVLink edge: messages to samples (units converted here, once).

GPS_RAW_INT: lat/lon degE7, alt mm, vel cm/s, cog cdeg (UINT16_MAX = unknown), h_acc mm,
vel_acc mm/s; fix_type < 3 is no 3D fix. RAW_IMU (ArduPilot): acceleration mG (specific force),
gyro mrad/s, magnetometer mGauss, body FRD. HIGHRES_IMU (PX4's, 50 Hz in its onboard mode): the same in
SI floats (m/s^2, rad/s, gauss), with EKF2's estimated sensor biases already taken out; its
fields_updated bits say which groups are new (a magnetometer without its bits is the last reading
again, and is not used); a non-finite value, or one beyond what RAW_IMU's int16 carries, is skipped.
ATTITUDE: roll, pitch rad; time_boot_ms; a roll outside [-pi, pi] or a pitch beyond 1.5 rad (or
either not finite) is skipped.
HEARTBEAT of an autopilot (autopilot != INVALID): its type; a GROUND_ROVER is a ground vehicle.

Read from a live link (`guard.sources.link`) and from tlog files (`guard.sources.tlog`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink.dialects.v20 import ardupilotmega as mavlink   # noqa: E402

from guard.model.samples import Attitude, GnssFix, ImuSample, Sample, VehicleType   # noqa: E402

G = 9.80665
UNKNOWN_U16 = 65535
MAX_EPH = 5_000                      # HDOP x 100: beyond 50 a fix is no fix, and the value is not used
WANTED = {mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, mavlink.MAVLINK_MSG_ID_RAW_IMU, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU,
          mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_HEARTBEAT}
IMU_MESSAGES = ("RAW_IMU", "HIGHRES_IMU")
HIGHRES_ACC_GYRO = 0b111111         # fields_updated: bits 0-2 the accelerometer, 3-5 the gyro ...
HIGHRES_MAG = 0b111 << 6            # ... 6-8 the magnetometer
# HIGHRES_IMU's floats bounded by what RAW_IMU's int16 carries: 32.767 g, rad/s and gauss; beyond, corrupt
ACC_MAX_MPS2, GYRO_MAX_RADPS, MAG_MAX_GAUSS = 32.767 * 9.80665, 32.767, 32.767


T_MAX_US = 4_102_444_800_000_000     # 2100-01-01 in unix microseconds: no boot or unix time goes past it
UNIX_MIN_US = 946_684_800_000_000    # 2000-01-01 in unix microseconds: a larger time_usec is UNIX time, not boot
ROLL_MAX_RAD = math.pi + 1e-6        # roll is in [-pi, pi]; float32(pi) is 8.7e-8 above pi


def to_sample(msg) -> tuple[Sample | None, str | None]:
    """Convert one decoded message to a sample, or (None, reason it was skipped). A time stamp past
    any boot or unix time (a forged or corrupted field) is dropped here, before any sink sees it."""
    name = msg.get_type()
    if name in ("GPS_RAW_INT", *IMU_MESSAGES) and not 0 <= msg.time_usec <= T_MAX_US:
        return None, "time_implausible"
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
        hdop = msg.eph / 100.0 if 0 < msg.eph < MAX_EPH else None     # HDOP x 100; UINT16_MAX: unknown
        return GnssFix(int(msg.time_usec), fix_ok, lat, lon, msg.alt / 1000.0, vn, ve,
                       h_acc / 1000.0 if h_acc else None, vel_acc / 1000.0 if vel_acc else None, hdop), None
    if name == "RAW_IMU":
        a, w = G / 1000.0, 1e-3
        mag = (msg.xmag, msg.ymag, msg.zmag)
        mx, my, mz = (None, None, None) if mag == (0, 0, 0) else (m / 1000.0 for m in mag)
        return ImuSample(int(msg.time_usec), msg.xacc * a, msg.yacc * a, msg.zacc * a,
                         msg.xgyro * w, msg.ygyro * w, msg.zgyro * w, mx, my, mz), None
    if name == "HIGHRES_IMU":
        return _highres_imu(msg)
    if name == "ATTITUDE":
        if not (abs(msg.roll) <= ROLL_MAX_RAD and abs(msg.pitch) <= 1.5):     # also NaN, inf
            return None, "attitude_non_finite"
        return Attitude(int(msg.time_boot_ms) * 1000, msg.roll, msg.pitch), None
    if name == "HEARTBEAT":
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:     # a ground station or a companion, not the vehicle
            return None, None
        return VehicleType(msg.type == mavlink.MAV_TYPE_GROUND_ROVER), None
    return None, None


def _highres_imu(msg) -> tuple[ImuSample | None, str | None]:
    """PX4's HIGHRES_IMU. A sender that fills no fields_updated (0) is taken at its values, a zero
    magnetometer being none; one that marks the accelerometer or the gyro as not new sent no new IMU
    sample."""
    acc_gyro = (msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro)
    if not all(math.isfinite(v) for v in acc_gyro):
        return None, "imu_invalid"
    if max(map(abs, acc_gyro[:3])) > ACC_MAX_MPS2 or max(map(abs, acc_gyro[3:])) > GYRO_MAX_RADPS:
        return None, "imu_out_of_range"
    updated = msg.fields_updated
    if updated and updated & HIGHRES_ACC_GYRO != HIGHRES_ACC_GYRO:
        return None, "imu_not_new"
    mag = (msg.xmag, msg.ymag, msg.zmag)
    fresh = updated & HIGHRES_MAG == HIGHRES_MAG if updated else mag != (0.0, 0.0, 0.0)
    if not (fresh and all(math.isfinite(m) and abs(m) <= MAG_MAX_GAUSS for m in mag)):
        mag = (None, None, None)
    return ImuSample(int(msg.time_usec), *acc_gyro, *mag), None


class ImuStream:
    """One IMU stream per vehicle. ArduPilot sends RAW_IMU; PX4 sends HIGHRES_IMU (and no RAW_IMU). A
    vehicle sending both would give the filter each motion twice, on two clocks: the kind heard first
    is read and the other counted (imu_other_stream), which is said once."""

    def __init__(self, say):
        self.say = say                          # how it is said: a log's notes, a link's log
        self.kind: str | None = None
        self._said = False

    def __call__(self, name: str) -> bool:
        """Whether an IMU message of this type is of the stream read."""
        if self.kind is None:
            self.kind = name
        if name == self.kind:
            return True
        if not self._said:
            self._said = True
            self.say(f"{name} is sent too: the IMU is read from {self.kind} alone, the one heard first")
        return False


class CompassRepeats:
    """RAW_IMU carries whatever magnetometer reading the autopilot holds: a compass slower than the
    stream (10 Hz in a 50 Hz RAW_IMU) sends each reading several times, and each would be a new
    measurement to the filter and its CUSUM, its error counted as often (an Erle copter's flights
    written as tlogs: 26 magnetometer alarms, against 13 from the same DataFlash logs, whose reader
    gives each reading once). The compass's own period is learnt from the stream over its first
    PERIOD_CHANGES changes of value, as the median of their spans over SPAN changes divided by SPAN (a
    compass a little slower than the stream, 75 Hz in 100 Hz, changes one or two samples apart, and
    the median of single gaps would be the stream's period); after that, a value equal to the last one
    taken, less than SAME_READING periods after it, is the same reading, and the sample goes on
    without it. A held reading is repeated for less than a period after it first came (its successor
    comes at the first sample after its own time); a noiseless compass (ArduPilot's SITL), or a
    quantised one as fast as the stream, reading the same value a period later is a new reading. One as
    fast as the stream never repeats, and nothing changes."""

    PERIOD_CHANGES = 20
    SPAN = 4
    SAME_READING = 1.0

    def __init__(self):
        self.period_us: float | None = None
        self._changes: list[int] = []
        self._last: tuple[int, tuple] | None = None    # (time, value) of the last reading taken

    def __call__(self, s: ImuSample) -> ImuSample:
        if s.mag_x_gauss is None:
            return s
        value, last = (s.mag_x_gauss, s.mag_y_gauss, s.mag_z_gauss), self._last
        if self.period_us is None:          # learning the period: every sample as it comes
            if last is None or value != last[1]:
                c = self._changes
                c.append(s.t_us)
                self._last = (s.t_us, value)
                if len(c) > self.PERIOD_CHANGES:
                    self.period_us = float(statistics.median(
                        (c[i + self.SPAN] - c[i]) / self.SPAN for i in range(len(c) - self.SPAN)))
            return s
        if value == last[1] and 0 <= s.t_us - last[0] < self.SAME_READING * self.period_us:
            return dataclasses.replace(s, mag_x_gauss=None, mag_y_gauss=None, mag_z_gauss=None)
        self._last = (s.t_us, value)
        return s


class UnixFixes:
    """GPS_RAW_INT.time_usec may be UNIX time: MAVLink lets the sender choose, and the receiver tells
    by the magnitude. Beside a RAW_IMU counting from boot, the fixes are then put on the boot clock,
    by the offset between the two that their arrival shows: the median, over the first OFFSET_FIXES
    fixes, of a fix's UNIX time less the boot time its arrival gives it (the latest IMU sample's, plus
    the time between their arrivals, by a tlog's prefix or a live link's clock: the link's latency
    jitter, milliseconds, against a whole flight). Said once. Without a boot-time IMU stream there is
    nothing to join, and the fixes stay as they came."""

    OFFSET_FIXES = 10

    def __init__(self, say):
        self.say = say                                  # how it is said: a log's notes, a link's log
        self._imu: tuple[int, int] | None = None        # (boot time, arrival) of the latest IMU sample
        self._seen: list[int] = []
        self.offset_us: int | None = None

    def imu(self, t_us: int, arrival_us: int | None) -> None:
        if arrival_us is not None:
            self._imu = (t_us, arrival_us)

    def fix(self, fix: GnssFix, arrival_us: int | None) -> GnssFix:
        if not fix.fix_ok or fix.t_us < UNIX_MIN_US or self._imu is None or self._imu[0] >= UNIX_MIN_US \
                or arrival_us is None:
            return fix
        if len(self._seen) < self.OFFSET_FIXES:
            self._seen.append(fix.t_us - (self._imu[0] + arrival_us - self._imu[1]))
            if self.offset_us is None:
                self.say("GPS_RAW_INT is stamped in UNIX time and RAW_IMU from boot: the fixes are put "
                                  "on the boot clock, by the offset their arrival shows")
            self.offset_us = int(statistics.median(self._seen))
        return dataclasses.replace(fix, t_us=fix.t_us - self.offset_us)
