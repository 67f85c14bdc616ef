"""MAVLink 2 output of the simulator: GPS_RAW_INT, RAW_IMU and HEARTBEAT in ArduPilot's units; as a PX4
autopilot (`Encoder(autopilot="px4")`) the IMU goes out as HIGHRES_IMU instead, as PX4's onboard link
sends it (SI floats; `fields_updated` marks the accelerometer, the gyro and the magnetometer new).

Two sinks: a tlog file (8-byte big-endian unix-microsecond prefix before every frame, written as
fast as possible) and a live pymavlink link (`udpout:127.0.0.1:14550`, `tcp:...`), which also
receives what the monitor sends back (STATUSTEXT), as an autopilot would.
"""

from __future__ import annotations

import copy
import math
import os
import struct

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink import mavutil                          # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink   # noqa: E402

from .sensors import G, ImuReading                     # noqa: E402

SYSTEM_ID = 1
COMPONENT_ID = mavlink.MAV_COMP_ID_AUTOPILOT1
TLOG_EPOCH_US = 1_767_225_600_000_000     # 2026-01-01T00:00:00Z: tlog prefix = epoch + simulated time


def _i16(x: float) -> int:
    return max(-32768, min(32767, int(round(x))))


def _u16(x: float) -> int:
    return max(0, min(65535, int(round(x))))


AUTOPILOTS = {"ardupilot": mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, "px4": mavlink.MAV_AUTOPILOT_PX4}
HIGHRES_ACC_GYRO_MAG = 0b111111111      # fields_updated: accelerometer, gyro and magnetometer new


class Encoder:
    """Builds the simulator's messages (one MAVLink instance keeps the sequence numbers). The run's
    messages are ArduPilot's; `pack` sends them as the autopilot chosen sends them."""

    def __init__(self, autopilot: str = "ardupilot"):
        if autopilot not in AUTOPILOTS:
            raise ValueError(f"autopilot {autopilot!r}: one of {', '.join(AUTOPILOTS)}")
        self.autopilot = autopilot
        self.mav = mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=COMPONENT_ID)

    def pack(self, msg) -> bytes:
        """Serialise one message with the next sequence number."""
        if self.autopilot == "px4" and msg.get_type() == "RAW_IMU":
            msg = self.highres_imu(msg)
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def heartbeat(self):
        return self.mav.heartbeat_encode(mavlink.MAV_TYPE_GROUND_ROVER, AUTOPILOTS[self.autopilot],
                                         mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_SAFETY_ARMED,
                                         10, mavlink.MAV_STATE_ACTIVE)

    def gps_raw_int(self, t_us: int, lat_deg: float, lon_deg: float, alt_m: float, vel_n: float, vel_e: float,
                    h_acc_m: float | None, vel_acc_mps: float | None, fix_type: int = 3):
        """GPS_RAW_INT. An accuracy of None (the receiver reports none) goes out as 0, MAVLink's "unknown";
        v_acc is 1.5 h_acc, and unknown with it."""
        speed = math.hypot(vel_n, vel_e)
        cog = math.degrees(math.atan2(vel_e, vel_n)) % 360.0
        h_acc = 0 if h_acc_m is None else int(round(h_acc_m * 1000))
        v_acc = 0 if h_acc_m is None else int(round(h_acc_m * 1500))
        vel_acc = 0 if vel_acc_mps is None else int(round(vel_acc_mps * 1000))
        return self.mav.gps_raw_int_encode(
            t_us, fix_type, int(round(lat_deg * 1e7)), int(round(lon_deg * 1e7)), int(round(alt_m * 1000)),
            100, 150, _u16(speed * 100), _u16(cog * 100) % 36000, 12,
            alt_ellipsoid=int(round(alt_m * 1000)), h_acc=h_acc, v_acc=v_acc, vel_acc=vel_acc, hdg_acc=0, yaw=0)

    def raw_imu(self, t_us: int, imu: ImuReading):
        acc = [_i16(a / G * 1000.0) for a in imu.acc_frd]          # mG
        gyro = [_i16(w * 1000.0) for w in imu.gyro_frd]            # mrad/s
        mag = [_i16(m * 1000.0) for m in imu.mag_frd]              # mGauss
        msg = self.mav.raw_imu_encode(t_us, *acc, *gyro, *mag, id=0, temperature=2500)
        # a compass slower than the IMU: RAW_IMU repeats its last reading, as an autopilot's does; the
        # simulator's other outputs (HIGHRES_IMU's bits, DataFlash's MAG, ULog's, DroneCAN's) carry each
        # reading once, as theirs do (not part of the MAVLink message: lost once it is packed)
        msg.mag_held = not imu.mag_fresh
        return msg

    def highres_imu(self, raw):
        """The same reading as PX4's HIGHRES_IMU: m/s^2, rad/s, gauss (RAW_IMU's resolution kept, so that
        the two carry the same numbers); a magnetometer of zeros (none), or a reading held since the last
        (Encoder.raw_imu), is not marked new."""
        mag = (raw.xmag / 1000.0, raw.ymag / 1000.0, raw.zmag / 1000.0)
        fresh = any(mag) and not getattr(raw, "mag_held", False)
        fields = HIGHRES_ACC_GYRO_MAG if fresh else HIGHRES_ACC_GYRO_MAG & 0b111111
        a = G / 1000.0
        return self.mav.highres_imu_encode(raw.time_usec, raw.xacc * a, raw.yacc * a, raw.zacc * a,
                                           raw.xgyro / 1000.0, raw.ygyro / 1000.0, raw.zgyro / 1000.0, *mag,
                                           1013.25, 0.0, 0.0, 25.0, fields, id=0)


class TlogWriter:
    """Writes frames with the tlog's time prefix."""

    def __init__(self, path: str, encoder: Encoder):
        self.f = open(path, "wb")
        self.encoder = encoder

    def send(self, t_us: int, msg) -> None:
        self.f.write(struct.pack(">Q", TLOG_EPOCH_US + t_us) + self.encoder.pack(msg))

    def close(self) -> None:
        self.f.close()


class LiveLink:
    """A pymavlink connection: sends our frames and hands back STATUSTEXT from other systems.

    As an autopilot's port, it may send GPS_RAW_INT and the IMU slower than the run makes them
    (`stream_hz`: at most that often, a port's default rates) until asked for more: a
    MAV_CMD_SET_MESSAGE_INTERVAL to this system sets a message's interval (0: back to the port's
    default, -1: off) and is acknowledged; each one honoured is passed to `on_request(name, interval_us)`.
    """

    def __init__(self, url: str, encoder: Encoder, stream_hz: float = 0.0, on_request=None):
        self.conn = mavutil.mavlink_connection(url, source_system=SYSTEM_ID, source_component=COMPONENT_ID,
                                               dialect="ardupilotmega", autoreconnect=True)
        self.encoder = encoder
        self.default_us = {n: 1e6 / stream_hz for n in ("GPS_RAW_INT", "RAW_IMU")} if stream_hz > 0 else {}
        self.interval_us = dict(self.default_us)       # message name -> at least this long between two
        self.last_us: dict[str, int] = {}
        self.on_request = on_request
        self._mag_unsent = False        # a compass reading not yet sent (send)

    def _due(self, t_us: int, name: str) -> bool:
        """Whether a message of this name goes out at t_us (a port's rate: the run's samples, thinned)."""
        if name == "HIGHRES_IMU":
            name = "RAW_IMU"
        interval = self.interval_us.get(name)
        if interval is None:
            return True
        last = self.last_us.get(name)
        if interval < 0 or last is not None and t_us - last < interval - 500:    # 0.5 ms: the run's sample grid
            return False
        self.last_us[name] = t_us
        return True

    def _command(self, msg) -> None:
        """A SET_MESSAGE_INTERVAL for this autopilot (system and component): honoured and acknowledged
        for a message it sends, denied for any other or for parameters that are no message id and
        interval."""
        if msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL or (msg.target_system, msg.target_component) != (
                SYSTEM_ID, COMPONENT_ID):
            return
        ok = all(math.isfinite(p) and abs(p) < 2 ** 31 for p in (msg.param1, msg.param2))
        entry = mavlink.mavlink_map.get(int(msg.param1)) if ok else None
        imu = "HIGHRES_IMU" if self.encoder.autopilot == "px4" else "RAW_IMU"
        result = mavlink.MAV_RESULT_DENIED
        if entry is not None and entry.msgname in ("GPS_RAW_INT", imu, "HEARTBEAT"):
            name = "RAW_IMU" if entry.msgname == "HIGHRES_IMU" else entry.msgname
            interval = round(msg.param2)
            if interval == 0:
                self.interval_us.pop(name, None)
                if name in self.default_us:
                    self.interval_us[name] = self.default_us[name]
            else:
                self.interval_us[name] = interval
            result = mavlink.MAV_RESULT_ACCEPTED
            if self.on_request:
                self.on_request(entry.msgname, interval)
        try:
            self.conn.write(self.encoder.pack(self.encoder.mav.command_ack_encode(msg.command, result)))
        except OSError:
            pass

    def send(self, t_us: int, msg) -> None:
        if msg.get_type() == "RAW_IMU":
            # a compass reading that came on a sample the port's rate left out is new on the next one sent
            # (PX4's HIGHRES_IMU marks what was updated since the last message it published)
            self._mag_unsent = self._mag_unsent or not getattr(msg, "mag_held", False)
        if not self._due(t_us, msg.get_type()):
            return
        if msg.get_type() == "RAW_IMU":
            if getattr(msg, "mag_held", False) and self._mag_unsent:
                msg = copy.copy(msg)
                msg.mag_held = False
            self._mag_unsent = False
        try:
            self.conn.write(self.encoder.pack(msg))
        except OSError:
            pass    # nobody listening yet (UDP refused): a real radio link drops frames too

    def receive(self, timeout_s: float):
        """Wait up to timeout_s for a STATUSTEXT from another system; None when none came."""
        msg = self.conn.recv_match(type=["STATUSTEXT", "COMMAND_LONG"], blocking=True, timeout=max(0.0, timeout_s))
        if msg is not None and msg.get_srcSystem() == SYSTEM_ID and msg.get_srcComponent() == COMPONENT_ID:
            return None
        if msg is not None and msg.get_type() == "COMMAND_LONG":
            self._command(msg)
            return None
        return msg

    def close(self) -> None:
        self.conn.close()
