"""Tiny valid inputs of every format guard reads: the fuzzers' seeds, built here from first principles.

Each is one second of a rover driving north at 5 m/s near 47.4 N 8.5 E: GNSS at 10 Hz, IMU at 20 Hz
(over the core's 8 Hz minimum), magnetometer and attitude at 10 Hz, and what each format adds (an
autopilot's text, its EKF's test ratios). Times are microseconds since boot (tlog prefixes: unix us).
The builders use struct (DataFlash, ULog), pymavlink (tlog, live bytes) and dronecan (CAN frames),
never the simulator, so that they stay independent of the code under test.

CAN frames travel as bytes in the fuzzers (`frames_to_bytes`, `bytes_to_frames`): per frame a
little-endian u32 (bit 31 extended id, bit 30 remote, bit 29 error frame, bits 0..28 the id), one byte
(bit 7 CAN FD, bits 0..6 the length, at most 64) and the data.
"""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink.dialects.v20 import ardupilotmega as mavlink    # noqa: E402

TLOG_EPOCH_US = 1_767_225_600_000_000       # 2026-01-01T00:00:00Z, the tlog prefix of boot time 0
T0_US = 5_000_000                           # the first sample, 5 s after boot
LAT0, LON0, ALT0 = 47.397742, 8.545594, 488.0
SPEED = 5.0                                 # m/s north
M_PER_DEG = 111_320.0
G = 9.80665
MAG_NED = (0.21, 0.0, 0.43)                 # gauss, a heading of 0 (north) near Zurich


def _truth(t_us: int) -> tuple[float, float, float]:
    """(lat, lon, alt) of the rover at t_us."""
    return LAT0 + SPEED * (t_us - T0_US) / 1e6 / M_PER_DEG, LON0, ALT0


def _ticks(hz: int, seconds: float = 1.0) -> list[int]:
    return [T0_US + round(k * 1e6 / hz) for k in range(round(seconds * hz))]


# -- MAVLink: live bytes and tlog ---------------------------------------------------------------------

def mavlink_messages() -> list[tuple[int, object]]:
    """(t_us, message) of one second, in time order: HEARTBEAT, GPS_RAW_INT, RAW_IMU, ATTITUDE and a
    SYS_STATUS (a type guard does not read)."""
    m = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    out = [(T0_US, m.heartbeat_encode(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)),
           (T0_US, m.sys_status_encode(0, 0, 0, 500, 12000, -1, 80, 0, 0, 0, 0, 0, 0))]
    for t in _ticks(10):
        lat, lon, alt = _truth(t)
        out.append((t, m.gps_raw_int_encode(t, 3, round(lat * 1e7), round(lon * 1e7), round(alt * 1000), 100, 150,
                                            round(SPEED * 100), 0, 12, alt_ellipsoid=round(alt * 1000),
                                            h_acc=1500, v_acc=2200, vel_acc=250, hdg_acc=0, yaw=0)))
        out.append((t, m.attitude_encode(t // 1000, 0.01, -0.02, 0.0, 0.0, 0.0, 0.0)))
    for t in _ticks(20):
        out.append((t, m.raw_imu_encode(t, 3, -2, -1000, 1, -1, 0, round(MAG_NED[0] * 1000), 0,
                                        round(MAG_NED[2] * 1000))))
    out.sort(key=lambda tm: tm[0])
    return out


def mavlink_bytes() -> bytes:
    """The live link's bytes: MAVLink 2 frames back to back."""
    m = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return b"".join(msg.pack(m) for _, msg in mavlink_messages())


def tlog() -> bytes:
    """A tlog: each frame after its 8-byte big-endian unix-microsecond prefix."""
    m = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return b"".join(struct.pack(">Q", TLOG_EPOCH_US + t) + msg.pack(m) for t, msg in mavlink_messages())


# -- ArduPilot DataFlash -----------------------------------------------------------------------------

DF_HEAD = b"\xa3\x95"
# type: (name, format characters, columns), ArduPilot's layouts cut to what guard reads
DF_FORMATS = {
    128: ("FMT", "BBnNZ", "Type,Length,Name,Format,Columns"),
    129: ("MSG", "QZ", "TimeUS,Message"),
    130: ("GPS", "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    131: ("GPA", "QBCCCC", "TimeUS,I,VDop,HAcc,VAcc,SAcc"),
    132: ("IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    133: ("MAG", "QBhhh", "TimeUS,I,MagX,MagY,MagZ"),
    134: ("ATT", "QccccCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
    135: ("XKF4", "QBccccc", "TimeUS,C,SV,SP,SH,SM,SVT"),
    136: ("ERR", "QBB", "TimeUS,Subsys,ECode"),
}
DF_STRUCT = {"B": "B", "b": "b", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d", "c": "h", "C": "H",
             "e": "i", "L": "i", "Q": "Q", "q": "q", "n": "4s", "N": "16s", "Z": "64s"}


def _df_struct(fmt: str) -> struct.Struct:
    return struct.Struct("<" + "".join(DF_STRUCT[c] for c in fmt))


def dataflash(formats: dict | None = None, edit=None) -> bytes:
    """An ArduPilot DataFlash log: FMT messages, then the rover's second of GPS/GPA, IMU, MAG, ATT,
    EKF3 test ratios (one above 1), a GPS error and the autopilot's texts.

    `formats` replaces entries of DF_FORMATS in the FMT messages only (the rows are still packed with
    DF_FORMATS: a corrupt FMT); `edit(name, t_us, values)` returns a row's values (None: leave it out)."""
    by_name = {name: (t, _df_struct(fmt)) for t, (name, fmt, _) in DF_FORMATS.items()}
    out = bytearray()

    def put(name: str, *values) -> None:
        t, s = by_name[name]
        out.extend(DF_HEAD + bytes((t,)) + s.pack(*values))

    for t, (name, fmt, cols) in {**DF_FORMATS, **(formats or {})}.items():
        put("FMT", t, 3 + _df_struct(DF_FORMATS[t][1]).size, name.encode(), fmt.encode(), cols.encode())
    rows = [(T0_US, 0, "MSG", ("ArduRover V4.5.7 (2e7bbc2d)".encode(),))]
    rows.append((T0_US, 1, "MSG", (b"GPS 1: detected u-blox at 230400 baud",)))
    rows.append((T0_US + 500_000, 1, "MSG", (b"GPS Glitch or Compass error",)))
    rows.append((T0_US + 500_000, 2, "ERR", (11, 2)))
    for t in _ticks(10):
        lat, lon, alt = _truth(t)
        rows.append((t, 3, "GPS", (0, 3, 300_000 + (t - T0_US) // 1000, 2400, 12, 70, round(lat * 1e7),
                                   round(lon * 1e7), round(alt * 100), SPEED, 0.0, 0.0, 0.0, 1)))
        rows.append((t, 4, "GPA", (0, 80, 150, 220, 25)))
        rows.append((t, 5, "MAG", (0, round(MAG_NED[0] * 1000), 0, round(MAG_NED[2] * 1000))))
        rows.append((t, 6, "ATT", (0, 57, 0, -115, 0, 0)))
    for t in _ticks(20):
        rows.append((t, 7, "IMU", (0, 0.001, -0.001, 0.0, 0.03, -0.02, -G)))
    for k, t in enumerate(_ticks(5)):
        rows.append((t, 8, "XKF4", (0, 30, 150 if k == 2 else 40, 20, 10, 0)))
    for t, _, name, values in sorted(rows, key=lambda r: r[:2]):
        values = edit(name, t, values) if edit else values
        if values is not None:
            put(name, t, *values)
    return bytes(out)


# -- PX4 ULog ----------------------------------------------------------------------------------------

UL_MAGIC = b"ULog\x01\x12\x35"
UL_TYPES = {"uint64_t": "Q", "int32_t": "i", "uint32_t": "I", "uint8_t": "B", "bool": "?", "float": "f",
            "double": "d"}
# topic -> fields (type, array size or 0, name), as PX4's msg/*.msg name them
UL_FORMATS = {
    "sensor_gps": [("uint64_t", 0, "timestamp"), ("double", 0, "latitude_deg"), ("double", 0, "longitude_deg"),
                   ("double", 0, "altitude_msl_m"), ("uint64_t", 0, "time_utc_usec"),
                   ("float", 0, "s_variance_m_s"), ("float", 0, "eph"), ("float", 0, "vel_n_m_s"),
                   ("float", 0, "vel_e_m_s"), ("uint8_t", 0, "fix_type"), ("bool", 0, "vel_ned_valid")],
    "sensor_combined": [("uint64_t", 0, "timestamp"), ("float", 3, "gyro_rad"),
                        ("int32_t", 0, "accelerometer_timestamp_relative"), ("float", 3, "accelerometer_m_s2")],
    "vehicle_magnetometer": [("uint64_t", 0, "timestamp"), ("float", 3, "magnetometer_ga")],
    "vehicle_attitude": [("uint64_t", 0, "timestamp"), ("float", 4, "q")],
    "vehicle_status": [("uint64_t", 0, "timestamp"), ("uint8_t", 0, "system_type"), ("uint8_t", 0, "vehicle_type")],
    "estimator_innovation_test_ratios": [("uint64_t", 0, "timestamp"), ("float", 2, "gps_hvel"),
                                         ("float", 2, "gps_hpos"), ("float", 0, "heading")],
}


def _ul(kind: str, body: bytes) -> bytes:
    return struct.pack("<HB", len(body), ord(kind)) + body


def _ul_struct(fields) -> struct.Struct:
    return struct.Struct("<" + "".join(f"{n or 1}{UL_TYPES[t]}" for t, n, _ in fields))


def ulog(edit=None) -> bytes:
    """A PX4 ULog (version 1): header, flag bits, an info, the formats and subscriptions, then the
    rover's second of topics in time order, with a sync message and a logged text about GPS.
    `edit(topic, t_us, values)` returns a record's values (without its timestamp; None: leave it out)."""
    out = bytearray(UL_MAGIC + b"\x01" + struct.pack("<Q", T0_US))
    out += _ul("B", bytes(16) + bytes(24))                          # flag bits: none, no appended data
    key = b"char[9] sys_name"
    out += _ul("I", bytes((len(key),)) + key + b"PX4_fuzzy")
    for name, fields in UL_FORMATS.items():
        out += _ul("F", (name + ":" + "".join(f"{t}{f'[{n}]' if n else ''} {f};" for t, n, f in fields)).encode())
    ids = {name: k for k, name in enumerate(UL_FORMATS)}
    for name, k in ids.items():
        out += _ul("A", struct.pack("<BH", 0, k) + name.encode())
    packers = {name: _ul_struct(fields) for name, fields in UL_FORMATS.items()}
    rows: list[tuple[int, int, str, tuple]] = [(T0_US, 0, "vehicle_status", (10, 3))]
    half = math.radians(0.5) / 2
    for t in _ticks(10):
        lat, lon, alt = _truth(t)
        rows.append((t, 1, "sensor_gps", (lat, lon, alt, TLOG_EPOCH_US + t, 0.25, 1.5, SPEED, 0.0, 3, True)))
        rows.append((t, 2, "vehicle_magnetometer", MAG_NED))
        rows.append((t, 3, "vehicle_attitude", (math.cos(half), math.sin(half), 0.0, 0.0)))
    for t in _ticks(20):
        rows.append((t, 4, "sensor_combined", (0.001, -0.001, 0.0, 0, 0.03, -0.02, -G)))
    for k, t in enumerate(_ticks(5)):
        rows.append((t, 5, "estimator_innovation_test_ratios", (0.2, 0.2, 1.7 if k == 2 else 0.3, 0.3, 0.1)))
    for t, _, name, values in sorted(rows, key=lambda r: r[:2]):
        values = edit(name, t, values) if edit else values
        if values is None:
            continue
        flat = [v for x in ((t,), values) for v in x]
        out += _ul("D", struct.pack("<H", ids[name]) + packers[name].pack(*flat))
        if t == T0_US + 500_000 and name == "sensor_gps":
            out += _ul("S", bytes((0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12)))
            out += _ul("L", struct.pack("<BQ", ord("4"), t) + b"GPS: receiver lost fix, using dead reckoning")
    return bytes(out)


# -- DroneCAN ----------------------------------------------------------------------------------------

EXTENDED, REMOTE, ERROR = 1 << 31, 1 << 30, 1 << 29
ID_MASK = (1 << 29) - 1
GNSS_NODE, IMU_NODE = 10, 11


def can_transfers(t_us: int = T0_US) -> list:
    """DroneCAN transfers (dronecan.transport.Transfer) of one GNSS fix, one magnetometer reading and
    two IMU samples, from the GNSS node 10 and the IMU node 11."""
    import dronecan
    from dronecan import transport
    eq = dronecan.uavcan.equipment
    fix = eq.gnss.Fix2()
    fix.timestamp.usec = t_us
    lat, lon, alt = _truth(t_us)
    fix.latitude_deg_1e8, fix.longitude_deg_1e8 = round(lat * 1e8), round(lon * 1e8)
    fix.height_msl_mm = fix.height_ellipsoid_mm = round(alt * 1000)
    fix.ned_velocity = [SPEED, 0.0, 0.0]
    fix.status, fix.sats_used = 3, 12
    fix.covariance = [2.25, 2.25, 4.0, 0.0625, 0.0625, 0.0625]
    mag = eq.ahrs.MagneticFieldStrength2()
    mag.magnetic_field_ga = list(MAG_NED)
    out = [transport.Transfer(transfer_id=0, source_node_id=GNSS_NODE, payload=fix, transfer_priority=20),
           transport.Transfer(transfer_id=0, source_node_id=IMU_NODE, payload=mag, transfer_priority=20)]
    for k in range(2):
        imu = eq.ahrs.RawIMU()
        imu.timestamp.usec = t_us + 50_000 * k
        imu.accelerometer_latest = [0.03, -0.02, -G]
        imu.rate_gyro_latest = [0.001, -0.001, 0.0]
        out.append(transport.Transfer(transfer_id=k, source_node_id=IMU_NODE, payload=imu, transfer_priority=10))
    return out


def raw_transfer_frames(dtid: int, node: int, payload: bytes, transfer_id: int = 0) -> list[tuple[int, bytes]]:
    """(can_id, data) of a message transfer carrying `payload` as it is (any bytes: fields a sender
    could not encode, float16 infinities), with the right transfer CRC for the data type."""
    import dronecan
    from dronecan import dsdl, transport
    kind = dronecan.DATATYPES[(dtid, dsdl.CompoundType.KIND_MESSAGE)]
    t = transport.Transfer(transfer_id=transfer_id, source_node_id=node, transfer_priority=20)
    t.payload, t.data_type_id, t.data_type_crc = bytes(payload), dtid, kind.base_crc
    return [(f.message_id, bytes(f.bytes)) for f in t.to_frames()]


def frames_to_bytes(frames) -> bytes:
    """(can_id, data, flags) triples, flags a set of "remote", "error", "fd", "standard", as bytes."""
    out = bytearray()
    for can_id, data, flags in frames:
        head = (can_id & ID_MASK) | (0 if "standard" in flags else EXTENDED)
        head |= (REMOTE if "remote" in flags else 0) | (ERROR if "error" in flags else 0)
        out += struct.pack("<IB", head, (0x80 if "fd" in flags else 0) | len(data)) + bytes(data)
    return bytes(out)


def bytes_to_frames(data: bytes) -> list[tuple[int, bytes, frozenset]]:
    """The inverse of frames_to_bytes, for any bytes: a length past 64 is taken modulo 65, a cut last
    frame keeps what is there."""
    frames, pos = [], 0
    while pos + 5 <= len(data):
        head, size = struct.unpack_from("<IB", data, pos)
        n = (size & 0x7F) % 65
        body = data[pos + 5:pos + 5 + n]
        flags = {name for bit, name in ((REMOTE, "remote"), (ERROR, "error")) if head & bit}
        flags |= set() if head & EXTENDED else {"standard"}
        flags |= {"fd"} if size & 0x80 else set()
        frames.append((head & ID_MASK, bytes(body), frozenset(flags)))
        pos += 5 + n
    return frames


def can_bytes() -> bytes:
    """The seed transfers' frames, in the fuzzers' byte form."""
    return frames_to_bytes((f.message_id, bytes(f.bytes), frozenset()) for t in can_transfers() for f in t.to_frames())


# -- the corpus --------------------------------------------------------------------------------------

def corpus() -> dict[str, dict[str, bytes]]:
    """target -> file name -> seed. The core's seed is a byte program (guard's `targets.samples_from`)."""
    from tools.fuzzing.targets import core_seed
    return {"mavlink": {"link.bin": mavlink_bytes()}, "tlog": {"drive.tlog": tlog()},
            "dataflash": {"drive.bin": dataflash()}, "ulog": {"drive.ulg": ulog()},
            "can": {"drive.can": can_bytes()}, "core": {"drive.core": core_seed()}}


def write_corpus(root: Path) -> list[Path]:
    """Write the seed corpus under root/TARGET/; the paths written."""
    written = []
    for target, files in corpus().items():
        (root / target).mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            (root / target / name).write_bytes(data)
            written.append(root / target / name)
    return written
