"""ArduPilot DataFlash (.bin) output of the simulator: the log an autopilot writes on its SD card.

pymavlink reads DataFlash (`pymavlink.DFReader`) but has no writer, so this one is written with
`struct`, to the layout DFReader and ArduPilot's `libraries/AP_Logger/LogStructure.h` describe:
every message is `0xA3 0x95 <type>` then a packed little-endian body; an FMT message (type 128)
first declares each type's name, format characters and column names, and FMTU/UNIT/MULT give the
columns' units (what MAVExplorer shows). The formats of GPS, GPA, IMU and MAG are those of
ArduPilot 4.x (`libraries/AP_GPS/LogStructure.h`, `AP_InertialSensor/LogStructure.h`,
`AP_Compass/LogStructure.h`), with an instance column `I`.

The simulator's MAVLink messages become, at their time `t_us` (boot time, microseconds):
- HEARTBEAT (the first) -> MSG with the firmware string of its vehicle type ("ArduRover V4.5.0").
- GPS_RAW_INT -> GPS (TimeUS, Status = fix_type, GWk/GMS, NSats, HDop, Lat/Lng degE7 as sent,
  Alt cm, Spd m/s, GCrs deg, VZ m/s) and GPA (HAcc, VAcc cm, SAcc cm/s, 0 when unknown, as in
  GPS_RAW_INT; SMS boot ms); GPS week and milliseconds come from the wall time
  `TLOG_EPOCH_US + t_us` (unix), GPS = UTC + 18 leap seconds.
- RAW_IMU -> MAG (MagX.. milligauss, as sent) then IMU (GyrX.. rad/s, AccX.. m/s^2 specific force,
  float32), body frame FRD. The MAG comes first so that a reader attaching the latest MAG to each
  IMU sample pairs the two taken together, as RAW_IMU does.
The IMU values are the RAW_IMU integers converted as guard's MAVLink edge converts them
(mG * 9.80665 / 1000, mrad/s / 1000), so a .bin and a tlog of one run carry the same numbers to
float32 precision; Alt (cm) and the accuracies (cm, cm/s) are rounded from the millimetres sent.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from functools import cached_property

from .mavout import TLOG_EPOCH_US
from .sensors import G

HEADER = b"\xa3\x95"
FIRMWARE_VERSION = "V4.5.0"
GPS_EPOCH_UNIX_S = 315_964_800          # 1980-01-06T00:00:00Z
LEAP_SECONDS = 18                        # GPS - UTC since 2017
WEEK_MS = 7 * 86_400_000

# DataFlash format character -> struct code (LogStructure.h; c, C, e, E hold value * 100, L degE7)
STRUCT_CODES = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d",
                "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I",
                "L": "i", "M": "B", "q": "q", "Q": "Q"}

# MAVLink MAV_TYPE -> ArduPilot firmware
ROVER_TYPES = {10, 11}                                  # GROUND_ROVER, SURFACE_BOAT
PLANE_TYPES = {1, 16, 19, 20, 21, 22, 23, 24, 25}       # FIXED_WING, FLAPPING_WING, VTOLs
COPTER_TYPES = {2, 3, 4, 13, 14, 15, 29}               # QUAD, COAXIAL, HELI, HEXA, OCTO, TRI, DODECA
SUB_TYPES = {12}


@dataclass(frozen=True)
class LogFormat:
    """One message type: its id, name, DataFlash format characters, columns and FMTU units."""

    type: int
    name: str
    format: str
    columns: str
    units: str = ""          # one unit id per column ('#' marks the instance column)
    mults: str = ""          # one multiplier id per column

    @cached_property
    def body(self) -> struct.Struct:
        return struct.Struct("<" + "".join(STRUCT_CODES[c] for c in self.format))

    @property
    def length(self) -> int:
        """Bytes of a message of this type, header included."""
        return 3 + self.body.size


FMT = LogFormat(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
UNIT = LogFormat(129, "UNIT", "QbZ", "TimeUS,Id,Label")
MULT = LogFormat(130, "MULT", "Qbd", "TimeUS,Id,Mult")
FMTU = LogFormat(131, "FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds")
MSG = LogFormat(132, "MSG", "QZ", "TimeUS,Message", "s-", "F-")
GPS = LogFormat(133, "GPS", "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
                "s#-s-S-DUmnhnh-", "F--C-0BGGB000--")
GPA = LogFormat(134, "GPA", "QBCCCCfBIHeHH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta,AEl,RTCMFU,RTCMFD",
                "s#-mmnd-ssm--", "F-BBBB0-CCB--")
IMU = LogFormat(135, "IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
                "s#EEEooo--O--zz", "F-000000-----00")
MAG = LogFormat(136, "MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",
                "s#GGGGGGGGG-s", "F-CCCCCCCCC-F")
FORMATS = (FMT, UNIT, MULT, FMTU, MSG, GPS, GPA, IMU, MAG)
UNITS = {"s": "s", "#": "instance", "-": "", "S": "satellites", "D": "deglatitude", "U": "deglongitude",
         "m": "m", "n": "m/s", "h": "degheading", "d": "deg", "E": "rad/s", "o": "m/s/s", "O": "degC",
         "z": "Hz", "G": "Gauss"}
MULTS = {"-": 0.0, "0": 1.0, "B": 1e-2, "C": 1e-3, "F": 1e-6, "G": 1e-7}


def gps_week_ms(unix_us: int) -> tuple[int, int]:
    """GPS week and milliseconds of the week of a unix time (microseconds)."""
    gps_ms = (unix_us // 1000) - GPS_EPOCH_UNIX_S * 1000 + LEAP_SECONDS * 1000
    return gps_ms // WEEK_MS, gps_ms % WEEK_MS


def firmware(mav_type: int) -> str:
    """The firmware string ArduPilot logs in its first MSG, for a HEARTBEAT vehicle type."""
    name = ("ArduRover" if mav_type in ROVER_TYPES else "ArduPlane" if mav_type in PLANE_TYPES
            else "ArduCopter" if mav_type in COPTER_TYPES else "ArduSub" if mav_type in SUB_TYPES
            else "ArduPilot")
    return f"{name} {FIRMWARE_VERSION}"


def _clamp(x: float, lo: int, hi: int) -> int:
    return max(lo, min(hi, int(round(x))))


def _accuracy_cm(mm: int) -> int:
    """A GPS_RAW_INT accuracy (mm or mm/s; 0: unknown) as GPA's HAcc/VAcc/SAcc (cm or cm/s; 0: unknown).

    0 is "unknown" in both: ArduPilot's AP_GPS::Write_GPS starts hacc, vacc and sacc at 0 and logs
    them so when the receiver gives none. A known accuracy under 5 mm is written as 1, not rounded
    to 0, so that it does not read as unknown.
    """
    return 0 if mm <= 0 else _clamp(mm / 10.0, 1, 65535)


class DataFlashWriter:
    """Writes the simulator's messages as an ArduPilot DataFlash log: send(t_us, msg), then close()."""

    def __init__(self, path: str):
        self.f = open(path, "wb")
        self.named = False          # the firmware MSG is written at the first HEARTBEAT
        self.last_gps_ms: int | None = None
        self._write_formats()

    def _write(self, fmt: LogFormat, *values) -> None:
        self.f.write(HEADER + bytes((fmt.type,)) + fmt.body.pack(*values))

    def _write_formats(self) -> None:
        for fmt in FORMATS:
            self._write(FMT, fmt.type, fmt.length, fmt.name.encode(), fmt.format.encode(), fmt.columns.encode())
        for uid, label in UNITS.items():
            self._write(UNIT, 0, ord(uid), label.encode())
        for mid, mult in MULTS.items():
            self._write(MULT, 0, ord(mid), mult)
        for fmt in FORMATS:
            if fmt.units:
                self._write(FMTU, 0, fmt.type, fmt.units.encode(), fmt.mults.encode())

    def send(self, t_us: int, msg) -> None:
        name = msg.get_type()
        if name == "HEARTBEAT" and not self.named:
            self._write(MSG, t_us, firmware(msg.type).encode())
            self.named = True
        elif name == "GPS_RAW_INT":
            self._gps(t_us, msg)
        elif name == "RAW_IMU":
            self._imu(t_us, msg)

    def _gps(self, t_us: int, m) -> None:
        week, week_ms = gps_week_ms(TLOG_EPOCH_US + t_us)
        unknown = m.vel == 65535 or m.cog == 65535
        speed = math.nan if unknown else m.vel / 100.0
        course = math.nan if unknown else m.cog / 100.0
        self._write(GPS, t_us, 0, m.fix_type, week_ms, week, m.satellites_visible, _clamp(m.eph, -32768, 32767),
                    m.lat, m.lon, _clamp(m.alt / 10.0, -2**31, 2**31 - 1), speed, course, 0.0, 0.0, 1)
        boot_ms = t_us // 1000
        delta = 0 if self.last_gps_ms is None else _clamp(boot_ms - self.last_gps_ms, 0, 65535)
        self.last_gps_ms = boot_ms
        self._write(GPA, t_us, 0, _clamp(m.epv, 0, 65535), _accuracy_cm(m.h_acc), _accuracy_cm(m.v_acc),
                    _accuracy_cm(m.vel_acc), 0.0, 0, boot_ms & 0xFFFFFFFF, delta,
                    _clamp(m.alt_ellipsoid / 10.0, -2**31, 2**31 - 1), 0, 0)

    def _imu(self, t_us: int, m) -> None:
        if not getattr(m, "mag_held", False):       # a slower compass: each reading once (Encoder.raw_imu)
            self._write(MAG, t_us, 0, m.xmag, m.ymag, m.zmag, 0, 0, 0, 0, 0, 0, 1, t_us & 0xFFFFFFFF)
        a, w = G / 1000.0, 1e-3         # mG -> m/s^2, mrad/s -> rad/s, as guard.sources.mavlink
        self._write(IMU, t_us, 0, m.xgyro * w, m.ygyro * w, m.zgyro * w, m.xacc * a, m.yacc * a, m.zacc * a,
                    0, 0, 25.0, 1, 1, 0, 0)

    def close(self) -> None:
        self.f.close()
