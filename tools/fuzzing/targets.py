"""The fuzz targets: bytes in, one of guard's decoders (or its core) run on them, the output checked.

Each target takes any bytes, runs its entry point the way guard does, checks every sample against
`contract.check_sample` and the reader's account against `contract.check_account`, and returns the
counts of what it saw. Only a target's documented errors (EXPECTED) may leave it: anything else, or a
`contract.Broken`, is a finding.

- mavlink: the live link's receive paths (guard.sources.link): guard's own framing
  (`guard.sources.framing.split`, as a datagram and as a stream) and pymavlink's parser (robust
  parsing on, `parse_buffer`), then `guard.sources.mavlink.to_sample` of each message.
- tlog, dataflash, ulog: the bytes as a file, read with `guard.sources.open_log` and `samples()`.
- can: the bytes as CAN frames (`seeds.bytes_to_frames`) through `CanSource`'s decode path.
- core: the bytes as a program of samples (`samples_from`) stepped through a fresh `Monitor`.

A random payload almost never passes a CRC, so the mavlink, tlog and can targets run their input
twice: as it is, and with every frame's (or transfer's) CRC made right, so that mutated fields reach
the conversion to samples.
"""

from __future__ import annotations

import atexit
import math
import os
import shutil
import struct
import tempfile
from collections import Counter
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink.dialects.v20 import ardupilotmega as mavlink    # noqa: E402

from guard.errors import SourceError                                     # noqa: E402
from guard.model.samples import Attitude, GnssFix, ImuSample, VehicleType   # noqa: E402
from guard.sources.mavlink import to_sample                              # noqa: E402
from tools.fuzzing import contract, seeds                                # noqa: E402

EXPECTED: dict[str, tuple[type[BaseException], ...]] = {
    "mavlink": (),                      # parse_buffer's MAVError is counted, as the link counts it
    "tlog": (SourceError,), "dataflash": (SourceError,), "ulog": (SourceError,),
    "can": (), "core": (),
}
READ_BYTES = 61                 # a serial read's size, prime to any frame length
SUFFIX = {"tlog": ".tlog", "dataflash": ".bin", "ulog": ".ulg"}
_scratch: Path | None = None


def _file(target: str, data: bytes) -> str:
    """`data` written to this process's scratch file of the target (in memory where /dev/shm is)."""
    global _scratch
    if _scratch is None:
        _scratch = Path(tempfile.mkdtemp(prefix="guard-fuzz-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
        atexit.register(shutil.rmtree, _scratch, ignore_errors=True)
    path = _scratch / f"input{SUFFIX[target]}"
    path.write_bytes(data)
    return str(path)


# -- CRCs made right ---------------------------------------------------------------------------------

def mavlink_crcs_fixed(data: bytes, prefix: int = 0) -> bytes:
    """`data` with the CRC of every MAVLink frame of a known type recomputed; frames are found as the
    tlog reader finds them (a start byte after `prefix` bytes of time, then the header's length)."""
    buf, pos = bytearray(data), 0
    while pos + prefix + 10 <= len(buf):
        stx = buf[pos + prefix]
        if stx not in (0xFD, 0xFE):
            pos += 1
            continue
        start = pos + prefix
        if stx == 0xFD:
            header, msgid = 10, buf[start + 7] | buf[start + 8] << 8 | buf[start + 9] << 16
        else:
            header, msgid = 6, buf[start + 5]
        end = start + header + buf[start + 1]
        kind = mavlink.mavlink_map.get(msgid)
        if end + 2 > len(buf) or kind is None:
            pos += 1
            continue
        crc = mavlink.x25crc(bytes(buf[start + 1:end]) + bytes((kind.crc_extra,))).crc
        buf[end:end + 2] = struct.pack("<H", crc)
        pos = end + 2 + (13 if stx == 0xFD and buf[start + 2] & 1 else 0)     # the next record's start
    return bytes(buf)


def can_crcs_fixed(frames: list) -> list:
    """Frames whose multi-frame transfers carry the right transfer CRC for their data type."""
    import dronecan
    from dronecan import dsdl
    from dronecan.dsdl import common
    out, open_ = [list(f) for f in frames], {}
    for k, (can_id, data, _) in enumerate(out):
        if not data:
            continue
        key, tail = (can_id, data[-1] & 0x1F), data[-1]
        if tail & 0x80:
            open_[key] = [k]
        elif key in open_:
            open_[key].append(k)
        if tail & 0x40 and key in open_:
            parts = open_.pop(key)
            kind = dronecan.DATATYPES.get(((can_id >> 8) & 0xFFFF, dsdl.CompoundType.KIND_MESSAGE))
            payload = b"".join(out[i][1][:-1] for i in parts)
            if len(parts) > 1 and kind is not None and len(payload) >= 2 and len(out[parts[0]][1]) >= 3:
                crc = common.crc16_from_bytes(payload[2:], initial=kind.base_crc)
                out[parts[0]][1] = struct.pack("<H", crc) + out[parts[0]][1][2:]
    return [tuple(f) for f in out]


# -- the targets -------------------------------------------------------------------------------------

def run_mavlink(data: bytes) -> Counter:
    """The live link's receive paths, on the bytes as they are (in one read) and with their CRCs made
    right (in reads of READ_BYTES, as from a serial port): pymavlink's parser, and guard's framing."""
    seen: Counter = Counter()
    for buf, step in ((data, len(data) or 1), (mavlink_crcs_fixed(data), READ_BYTES)):
        seen.update(run_framing(buf, step))
        mav = mavlink.MAVLink(None)
        mav.robust_parsing = True         # as mavutil's connections parse
        messages = []
        for at in range(0, len(buf), step):
            try:
                messages += mav.parse_buffer(buf[at:at + step]) or []
            except mavlink.MAVError:
                seen["bad_frame"] += 1
        for msg in messages:
            if msg.get_type() == "BAD_DATA":
                seen["bad_data"] += 1
                continue
            tally(msg, seen)
    return seen


def tally(msg, seen: Counter) -> None:
    """One decoded message through to_sample: its sample checked against the contract, counted."""
    sample, reason = to_sample(msg)
    if sample is not None:
        contract.check_sample(sample)
        seen[type(sample).__name__] += 1
    elif reason:
        seen[reason] += 1


def run_framing(buf: bytes, step: int) -> Counter:
    """guard.sources.framing as the link uses it: the bytes as one datagram, and as a stream read in
    pieces of `step` bytes (the tail kept for the next read); each frame decoded, then to_sample."""
    from guard.sources import framing
    seen: Counter = Counter()
    found = framing.split(buf, final=True)
    frames, tail = list(found.frames), b""
    for at in range(0, len(buf), step):
        part = framing.split(tail + buf[at:at + step], final=False)
        frames += part.frames
        tail = (tail + buf[at:at + step])[part.rest:]
        seen["bad_frame"] += part.bad
    mav = mavlink.MAVLink(None)
    for frame in frames:
        try:
            msg = mav.decode(bytearray(frame.buf))
        except mavlink.MAVError:
            seen["bad_frame"] += 1
            continue
        tally(msg, seen)
    return +seen


def run_log(target: str, data: bytes) -> Counter:
    """A log file through open_log and its reader's samples()."""
    from guard.sources import open_log
    seen: Counter = Counter()
    with open_log(_file(target, data)) as reader:
        for sample in reader.samples():
            contract.check_sample(sample)
            seen[type(sample).__name__] += 1
        contract.check_account(reader)
        seen.update(reader.skipped)
    return seen


def run_tlog(data: bytes) -> Counter:
    seen = Counter()
    for buf in (data, mavlink_crcs_fixed(data, prefix=8)):
        try:
            seen.update(run_log("tlog", buf))
        except SourceError:
            seen["source_error"] += 1
    return seen


def run_can(data: bytes) -> Counter:
    """CAN frames through CanSource's bridge and decoding, as they are and with their CRCs made right."""
    import can
    from guard.sources.can import CanSource
    seen: Counter = Counter()
    frames = seeds.bytes_to_frames(data)
    for batch in (frames, can_crcs_fixed(frames)):
        source = CanSource(f"can:virtual:guard-fuzz-{os.getpid()}", gnss_node_id=None, imu_node_id=None)
        try:
            for k, (can_id, body, flags) in enumerate(batch):
                fd = "fd" in flags
                msg = can.Message(timestamp=1_700_000_000.0 + k * 1e-3, arbitration_id=can_id,
                                  is_extended_id="standard" not in flags, is_remote_frame="remote" in flags,
                                  is_error_frame="error" in flags, is_fd=fd,
                                  data=body if fd or len(body) <= 8 else body[:8], check=False)
                sample = source._on_message(msg)
                if sample is not None:
                    contract.check_sample(sample)
                    seen[type(sample).__name__] += 1
            seen.update({k: n for k, n in source.stats.items() if n})
        finally:
            source.close()
    return seen


def run_core(data: bytes) -> Counter:
    """The samples the bytes describe, stepped through a fresh Monitor."""
    from guard.core.monitor import Monitor
    monitor, seen = Monitor(), Counter()
    for sample in samples_from(data):
        events = monitor.step(sample)
        contract.check_events(events)
        seen.update(type(e).__name__ for e in events)
    contract.check_events(monitor.finish())
    return seen


TARGETS = {"mavlink": run_mavlink, "tlog": run_tlog, "dataflash": lambda d: run_log("dataflash", d),
           "ulog": lambda d: run_log("ulog", d), "can": run_can, "core": run_core}


def run(target: str, data: bytes) -> Counter:
    """Run a target; its documented errors are counted (as `error`), anything else goes up."""
    try:
        return TARGETS[target](data)
    except EXPECTED[target] as e:
        return Counter({f"error {type(e).__name__}": 1})


# -- the core's byte program ------------------------------------------------------------------------

RECORD = struct.Struct("<Bh9h")         # op, time code, nine values (each -32767..32767 -> -1..1)
TIME_SCALE_US = (10, 1_000, 100_000, 10_000_000)    # op bits 5-6: a step of dt * this (bit 7: absolute)
LAT0, LON0, ALT0 = seeds.LAT0, seeds.LON0, seeds.ALT0


def _u(q: int) -> float:
    return max(-1.0, q / 32767.0)


def _cube(q: int, limit: float) -> float:
    """-1..1 cubed times limit: fine steps near zero (ordinary values), the envelope's edge at the ends."""
    return limit * _u(q) ** 3


def _decades(q: int, top: float) -> float:
    """0 .. top, evenly in decades: 10**(|u| log10(top + 1)) - 1."""
    return min(top, 10.0 ** (abs(_u(q)) * math.log10(top + 1.0)) - 1.0)


def _clip(x: float, limit: float) -> float:
    return min(limit, max(-limit, x))


def samples_from(data: bytes) -> list:
    """Samples from bytes, RECORD by RECORD: op bits 0-1 the kind (GNSS, IMU, attitude, vehicle),
    bit 2 no fix / no magnetometer / ground, bit 3 no velocity, bit 4 no accuracies; the time moves
    by the time code times TIME_SCALE_US[bits 5-6], or with bit 7 is the time code's magnitude times
    2**37 (0 .. the envelope's end). Every value is inside `contract`'s envelope."""
    c = contract
    out, t = [], seeds.T0_US
    for k in range(len(data) // RECORD.size):
        op, dt, *q = RECORD.unpack_from(data, k * RECORD.size)
        if op & 0x80:
            t = min(abs(dt) << 37, c.T_MAX_US)
        else:
            t = max(0, min(c.T_MAX_US, t + dt * TIME_SCALE_US[op >> 5 & 3]))
        kind, flag = op & 3, bool(op & 4)
        if kind == 0:
            fix = not flag
            lat, lon = LAT0 + _cube(q[0], 180.0), LON0 + _cube(q[1], 360.0)
            lat, lon = (_clip(lat, 90.0), _clip(lon, 180.0)) if fix else (lat, lon)
            if fix and (lat, lon) == (0.0, 0.0):
                lat = 1e-7
            vn, ve = (None, None) if op & 8 else (_cube(q[3], c.SPEED_MAX_MPS), _cube(q[4], c.SPEED_MAX_MPS))
            h_acc, vel_acc = (None, None) if op & 16 else (_decades(q[5], c.ACCURACY_MAX),
                                                           _decades(q[6], c.ACCURACY_MAX))
            alt = ALT0 + math.copysign(10.0 ** (300 * _u(q[2]) ** 4) - 1.0, q[2])     # up to 1e300 m
            out.append(GnssFix(t, fix, lat, lon, alt, vn, ve, h_acc, vel_acc))
        elif kind == 1:
            acc = [_cube(v, c.ACC_MAX_MPS2) for v in q[0:3]]
            gyro = [_cube(v, c.GYRO_MAX_RADPS) for v in q[3:6]]
            mag = [None] * 3 if flag else [_cube(v, c.MAG_MAX_GAUSS) for v in q[6:9]]
            out.append(ImuSample(t, *acc, *gyro, *mag))
        elif kind == 2:
            out.append(Attitude(t, _clip(_u(q[0]) * math.pi, math.pi), _u(q[1]) * c.PITCH_MAX_RAD))
        else:
            out.append(VehicleType(flag))
    return out


def _q(value: float, limit: float, power: int = 3) -> int:
    """The value code nearest to `value` under value = limit * u**power."""
    u = math.copysign(abs(value / limit) ** (1 / power), value)
    return round(max(-1.0, min(1.0, u)) * 32767)


def _q_decades(value: float, top: float) -> int:
    return round(math.log10(value + 1.0) / math.log10(top + 1.0) * 32767)


def core_seed() -> bytes:
    """The rover's second as a byte program: a vehicle type, then GNSS at 10 Hz, IMU at 20 Hz, in 10 ms steps."""
    c, out = contract, bytearray(RECORD.pack(4 | 3, 0, *[0] * 9))
    acc_q = [_q(v, c.ACC_MAX_MPS2) for v in (0.03, -0.02, -seeds.G)]
    gyro_q = [_q(v, c.GYRO_MAX_RADPS) for v in (0.001, -0.001, 0.0)]
    mag_q = [_q(v, c.MAG_MAX_GAUSS) for v in seeds.MAG_NED]
    for k in range(100):
        if k % 10 == 0:
            lat = seeds.LAT0 + seeds.SPEED * k / 100 / seeds.M_PER_DEG
            q = [_q(lat - LAT0, 180.0), 0, 0, _q(seeds.SPEED, c.SPEED_MAX_MPS), 0,
                 _q_decades(1.5, c.ACCURACY_MAX), _q_decades(0.25, c.ACCURACY_MAX), 0, 0]
            out += RECORD.pack(0 | 1 << 5, 50 if k else 0, *q)
        if k % 5 == 0:
            out += RECORD.pack(1 | 1 << 5, 0 if k % 10 == 0 else 50, *acc_q, *gyro_q, *mag_q)
    return bytes(out)
