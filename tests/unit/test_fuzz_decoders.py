"""One bad frame must never stop the monitor: property-based tests of every decoder.

Whatever comes in (field values a sender could put on the wire, NaN and infinities included; bytes
mutated, cut or made up), a decoder raises nothing but guard's documented errors (a log that cannot
be read: SourceError), every sample it emits keeps the promises of tools/fuzzing/contract.py (finite,
SI units, in physical range), and what it drops is counted under a reason.

Inputs are built by hand (tools/fuzzing/seeds.py: struct, pymavlink, dronecan), never by the
simulator. Derandomized, without an example database: every run tries the same examples, each test
takes seconds; tools/fuzz.py runs the same targets at scale, coverage-guided. Below the properties,
one regression test per failure the fuzzer found.
"""

import math
import signal
import struct
import sys
from collections import Counter
from pathlib import Path

import guard.sources.mavlink  # noqa: F401  (MAVLINK20=1 before pymavlink is imported)
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from guard.errors import SourceError
from guard.model.samples import Attitude, GnssFix, ImuSample
from guard.sources.can import FIX2, MAG2, RAW_IMU, CanSource
from guard.sources.mavlink import to_sample

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))    # tools.fuzzing, beside guard
from tools.fuzzing import contract, seeds, targets  # noqa: E402


def fuzz(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


TLOG, DATAFLASH, ULOG = seeds.tlog(), seeds.dataflash(), seeds.ulog()
INTERESTING = [struct.pack("<f", math.nan), struct.pack("<f", -math.inf), struct.pack("<d", 1e308),
               struct.pack("<i", -2**31), struct.pack("<Q", 2**64 - 1), b"\xfd", b"\xa3\x95\x80", b"\x00" * 8]


@st.composite
def mutated(draw, seed: bytes):
    """`seed` with a few bytes flipped, overwritten, inserted or deleted, then perhaps cut."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 6))):
        i = draw(st.integers(0, max(len(data) - 1, 0)))
        op = draw(st.sampled_from(["flip", "byte", "insert", "delete", "value"]))
        if op == "flip" and data:
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte" and data:
            data[i] = draw(st.integers(0, 255))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=24))
        elif op == "delete":
            del data[i:i + draw(st.integers(1, 24))]
        else:
            value = draw(st.sampled_from(INTERESTING))
            data[i:i + len(value)] = value
    if draw(st.booleans()):
        del data[draw(st.integers(0, len(data))):]
    return bytes(data)


def read(path_or_bytes, suffix: str = ".tlog", tmp_path=None):
    """(samples, reader) of a log, every sample checked against the contract."""
    from guard.sources import open_log
    path = tmp_path / f"log{suffix}"
    path.write_bytes(path_or_bytes)
    with open_log(str(path)) as reader:
        out = list(reader.samples())
        for s in out:
            contract.check_sample(s)
        contract.check_account(reader)
    return out, reader


# -- the MAVLink edge: to_sample of any field values ---------------------------------------------------

INT_RANGES = {"int8_t": (-2**7, 2**7 - 1), "uint8_t": (0, 2**8 - 1), "int16_t": (-2**15, 2**15 - 1),
              "uint16_t": (0, 2**16 - 1), "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1),
              "int64_t": (-2**63, 2**63 - 1), "uint64_t": (0, 2**64 - 1)}


def field(ftype: str):
    if ftype in INT_RANGES:
        return st.integers(*INT_RANGES[ftype])
    return st.floats(width=32 if ftype == "float" else 64)          # NaN and infinities included


@st.composite
def wire_message(draw, cls):
    """A message of class `cls` with any values its field types carry, through MAVLink 2 bytes."""
    values = [draw(field(t) if n == 0 else st.lists(field(t), min_size=n, max_size=n))
              for t, n in zip(cls.fieldtypes, cls.array_lengths)]
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return mavlink.MAVLink(None).decode(bytearray(cls(*values).pack(sender)))


EDGE_TYPES = [mavlink.MAVLink_gps_raw_int_message, mavlink.MAVLink_raw_imu_message,
              mavlink.MAVLink_attitude_message, mavlink.MAVLink_heartbeat_message,
              mavlink.MAVLink_global_position_int_message]      # the last: a type the edge does not read


@pytest.mark.parametrize("cls", EDGE_TYPES, ids=lambda c: c.msgname)
@fuzz(300)
@given(data=st.data())
def test_to_sample_of_any_field_values(cls, data):
    msg = data.draw(wire_message(cls))
    sample, reason = to_sample(msg)
    if sample is not None:
        assert reason is None
        contract.check_sample(sample)
    elif msg.get_type() in ("GPS_RAW_INT", "RAW_IMU", "ATTITUDE"):
        assert isinstance(reason, str) and reason, "a dropped sample is counted under a reason"


# -- the live link's receive path: pymavlink's parser, then to_sample ---------------------------------

@fuzz(150)
@given(data=st.binary(max_size=800) | mutated(seeds.mavlink_bytes()))
def test_live_bytes(data):
    seen = targets.run_mavlink(data)                # checks every sample; raises on anything else
    assert all(n > 0 for n in seen.values())


# -- tlog ----------------------------------------------------------------------------------------------

@fuzz(120)
@given(data=st.binary(max_size=1500) | mutated(TLOG))
def test_tlog_of_any_bytes(data):
    targets.run_tlog(data)                          # as it is, and with every frame's CRC made right


def record_ends(data: bytes) -> list[int]:
    """Where each record of a tlog ends (its prefix, its MAVLink 2 frame)."""
    ends, pos = [], 0
    while pos < len(data):
        pos += 8 + 12 + data[pos + 9]
        ends.append(pos)
    return ends


@fuzz(60)
@given(cut=st.integers(1, len(TLOG) - 1))
def test_a_cut_tlog_keeps_what_came_before_and_counts_the_cut(cut, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tlog")
    whole, _ = read(TLOG, ".tlog", tmp)
    part, reader = read(TLOG[:cut], ".tlog", tmp)
    assert part == whole[:len(part)]
    if cut not in record_ends(TLOG):
        assert reader.skipped["truncated"] == 1, dict(reader.skipped)
    assert reader.skipped.get("garbage_bytes", 0) <= cut


# -- DataFlash -----------------------------------------------------------------------------------------

@fuzz(120)
@given(data=mutated(DATAFLASH))
def test_dataflash_of_mutated_bytes(data):
    targets.run("dataflash", data)          # SourceError is documented; the rest goes up


def dataflash_ends(data: bytes) -> list[int]:
    lengths = {t: 3 + seeds._df_struct(fmt).size for t, (_, fmt, _) in seeds.DF_FORMATS.items()}
    ends, pos = [], 0
    while pos < len(data):
        pos += lengths[data[pos + 2]]
        ends.append(pos)
    return ends


@fuzz(60)
@given(cut=st.integers(dataflash_ends(DATAFLASH)[len(seeds.DF_FORMATS) - 1] + 1, len(DATAFLASH) - 1))
def test_a_cut_dataflash_log_counts_the_cut(cut, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bin")
    whole, _ = read(DATAFLASH, ".bin", tmp)
    part, reader = read(DATAFLASH[:cut], ".bin", tmp)
    assert [(type(s), getattr(s, "t_us", 0)) for s in part] == \
        [(type(s), getattr(s, "t_us", 0)) for s in whole[:len(part)]]
    if cut not in dataflash_ends(DATAFLASH):
        assert reader.skipped["truncated"] == 1, dict(reader.skipped)


# -- ULog ----------------------------------------------------------------------------------------------

@fuzz(120)
@given(data=mutated(ULOG))
def test_ulog_of_mutated_bytes(data):
    targets.run("ulog", data)


def ulog_message_ends(data: bytes) -> list[int]:
    ends, pos = [], 16
    while pos < len(data):
        pos += 3 + struct.unpack_from("<H", data, pos)[0]
        ends.append(pos)
    return ends


DATA_START = ULOG.index(b"\x00D", 16) - 1           # the first data message (its size's first byte)


@fuzz(60)
@given(cut=st.integers(DATA_START + 1, len(ULOG) - 1))
def test_a_cut_ulog_counts_the_cut(cut, tmp_path_factory):
    part, reader = read(ULOG[:cut], ".ulg", tmp_path_factory.mktemp("ulg"))
    if cut not in ulog_message_ends(ULOG):
        assert reader.skipped["truncated"] == 1, dict(reader.skipped)


# -- DroneCAN ------------------------------------------------------------------------------------------

def feed(frames) -> tuple[list, CanSource]:
    """(can_id, data) or (can_id, data, flags) frames through a fresh CanSource's decoding; the samples
    (checked) and the source."""
    import can
    source = CanSource("can:virtual:guard-fuzz-test", gnss_node_id=None, imu_node_id=None)
    out = []
    try:
        for k, (can_id, data, *flags) in enumerate(frames):
            flags = flags[0] if flags else frozenset()
            msg = can.Message(timestamp=1e9 + k * 1e-3, arbitration_id=can_id, data=data,
                              is_extended_id="standard" not in flags, is_remote_frame="remote" in flags,
                              is_error_frame="error" in flags, check=False)
            sample = source._on_message(msg)
            if sample is not None:
                contract.check_sample(sample)
                out.append(sample)
    finally:
        source.close()
    return out, source


can_frames = st.lists(st.tuples(st.integers(0, 2**29 - 1), st.binary(max_size=8),
                                st.frozensets(st.sampled_from(["standard", "remote", "error"]), max_size=1)),
                      max_size=40)


@fuzz(150)
@given(frames=can_frames)
def test_any_can_frames(frames):
    feed(frames)


@fuzz(200)
@given(transfers=st.lists(st.tuples(st.sampled_from([FIX2, RAW_IMU, MAG2]), st.binary(max_size=90)),
                          min_size=1, max_size=6))
def test_dronecan_transfers_of_any_payload(transfers):
    """Well-framed transfers (right CRC) of the types guard reads, whatever their payload: each one is
    a sample, a magnetometer reading, or counted."""
    frames = [f for k, (dtid, payload) in enumerate(transfers)
              for f in seeds.raw_transfer_frames(dtid, 10, payload, transfer_id=k)]
    samples, source = feed(frames)
    accounted = len(samples) + source.stats["bad_transfer"] + source.stats["bad_value"] \
        + source.stats["no_timestamp"] + source.stats["gnss_bad_position"] + source.stats["other_sensor"] \
        + sum(1 for dtid, _ in transfers if dtid == MAG2)
    assert accounted >= len(transfers), (dict(source.stats), len(samples))


# -- regressions: what the fuzzer found ----------------------------------------------------------------

def attitude(roll: float, pitch: float = 0.0):
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return mavlink.MAVLink(None).decode(bytearray(sender.attitude_encode(1000, roll, pitch, 0, 0, 0, 0).pack(sender)))


@pytest.mark.parametrize("roll", [3.2, -4.0, 9.6e26, math.inf, math.nan])
def test_mavlink_roll_outside_pi_is_skipped(roll):
    """ATTITUDE.roll is in [-pi, pi]: 9.6e26 came through a mutated tlog and rode on the IMU samples."""
    assert to_sample(attitude(roll)) == (None, "attitude_non_finite")


def test_mavlink_roll_of_pi_in_float32_is_kept():
    sample, reason = to_sample(attitude(-math.pi))
    assert reason is None and isinstance(sample, Attitude) and sample.roll_rad == pytest.approx(-math.pi)


def test_dataflash_roll_beyond_180_degrees_is_skipped(tmp_path):
    """ATT.Roll is int16 centidegrees: up to 327.67 degrees on the wire, corrupt beyond 180."""
    def edit(name, t, values):
        return (values[0], -20000, *values[2:]) if name == "ATT" and t % 200_000 == 0 else values
    samples, reader = read(seeds.dataflash(edit=edit), ".bin", tmp_path)
    assert reader.skipped["attitude_non_finite"] == 5
    assert sum(isinstance(s, Attitude) for s in samples) == 5


def test_dataflash_format_naming_more_columns_than_it_has(tmp_path):
    """An FMT whose columns outnumber its format characters (a corrupt byte): the IMU's AccZ has no
    value. Its rows are bad messages; the rest of the log is read (was an IndexError out of samples())."""
    imu = seeds.DF_FORMATS[132]
    samples, reader = read(seeds.dataflash(formats={132: (imu[0], imu[1][:-1], imu[2])}), ".bin", tmp_path)
    kinds = Counter(type(s).__name__ for s in samples)
    assert kinds["ImuSample"] == 0 and kinds["GnssFix"] == 10 and kinds["Attitude"] == 10
    assert reader.skipped["bad_message"] == 20


def test_dataflash_gps_without_a_position_column(tmp_path):
    """A GPS format cut short (a corrupt FMT) leaves Lat, Lng and Alt without a value: its rows without
    a fix came out with a position of None."""
    gps = seeds.DF_FORMATS[130]

    def no_fix(name, t, values):
        return (values[0], 1, *values[2:]) if name == "GPS" else values
    samples, reader = read(seeds.dataflash(formats={130: (gps[0], gps[1][:7], gps[2])}, edit=no_fix), ".bin", tmp_path)
    assert not any(isinstance(s, GnssFix) for s in samples) and reader.skipped["bad_message"] == 10


def test_dataflash_magnetometer_not_finite(tmp_path):
    """MAG declared as floats (a corrupt FMT) reads NaN: the reading is a bad message, not a NaN
    riding on the IMU samples."""
    mag = seeds.DF_FORMATS[133]

    def nan_bits(name, t, values):            # MagX, MagY as one float32: 00 00 c0 7f, a NaN
        return (0, 0, 0x7FC0, values[3]) if name == "MAG" else values
    samples, reader = read(seeds.dataflash(formats={133: (mag[0], "QBfhh", mag[2])}, edit=nan_bits), ".bin",
                           tmp_path)
    imu = [s for s in samples if isinstance(s, ImuSample)]
    assert len(imu) == 20 and all(s.mag_x_gauss is None for s in imu)
    assert reader.skipped["bad_message"] == 10


def test_ulog_fix_less_position_that_is_not_finite(tmp_path):
    """A sensor_gps record without a fix whose position bytes are NaN: still a sample (the core says
    the fix is lost), its meaningless position 0 rather than NaN."""
    def edit(name, t, values):
        if name == "sensor_gps" and t < seeds.T0_US + 300_000:
            return (math.nan, math.inf, math.nan, *values[3:8], 0, False)
        return values
    samples, reader = read(seeds.ulog(edit=edit), ".ulg", tmp_path)
    fixes = [s for s in samples if isinstance(s, GnssFix)]
    assert len(fixes) == 10 and [f.fix_ok for f in fixes[:4]] == [False, False, False, True]
    assert (fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].alt_m) == (0.0, 0.0, 0.0)


class Hung(Exception):
    """Past the time limit (guard's ULog loader turns it into a SourceError that names it)."""


def test_ulog_cut_inside_a_corrupt_definition_does_not_loop(tmp_path):
    """A definitions message of type 0 (corrupt) whose size runs past the end of the file: pyulog
    stepped back by the size it asked for, landed on an earlier message, and read the same bytes again
    for ever (found by the tlog target: open_log goes by the content, and the bytes had become a ULog)."""
    starts = [16]
    while ULOG[starts[-1] + 2] != ord("A"):         # the definitions, up to the first subscription
        starts.append(starts[-1] + 3 + struct.unpack_from("<H", ULOG, starts[-1])[0])
    end, back_to = starts[-1], starts[-2]
    data = ULOG[:end] + struct.pack("<HB", end + 1 + 20 - back_to, 0) + bytes(20)

    def hung(*_):
        raise Hung("pyulog still reading after 20 s")
    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(20)
    try:
        samples, reader = read(data, ".ulg", tmp_path)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert samples == [] and reader.skipped["ulog_corrupt"] == 1 and reader.skipped["truncated"] == 1


def imu_payload(acc=(1.0, 2.0, 3.0), t_us=seeds.T0_US) -> bytearray:
    import dronecan
    from dronecan import transport
    m = dronecan.uavcan.equipment.ahrs.RawIMU()
    m.timestamp.usec = t_us
    m.accelerometer_latest = list(acc)
    m.rate_gyro_latest = [0.0, 0.0, 0.0]
    return bytearray(transport.Transfer(source_node_id=11, payload=m).payload)


@pytest.mark.parametrize("value", [b"\x00\x7c", b"\x00\xfc", b"\x01\x7e", b"\xff\x7b"])   # inf, -inf, NaN, 65504
def test_can_imu_value_not_finite_or_beyond_any_sensor(value):
    """RawIMU's float16 accelerometer reading of inf, NaN or 65504 m/s^2 was passed on as a sample."""
    payload = imu_payload()
    at = payload.index(struct.pack("<e", 2.0))
    payload[at:at + 2] = value
    samples, source = feed(seeds.raw_transfer_frames(RAW_IMU, 11, bytes(payload)))
    assert samples == [] and source.stats["bad_value"] == 1


def test_can_imu_time_stamp_past_2100():
    samples, source = feed(seeds.raw_transfer_frames(RAW_IMU, 11, bytes(imu_payload(t_us=2**56 - 1))))
    assert samples == [] and source.stats["bad_value"] == 1
    samples, _ = feed(seeds.raw_transfer_frames(RAW_IMU, 11, bytes(imu_payload())))
    assert len(samples) == 1 and isinstance(samples[0], ImuSample)


def fix2(**values):
    import dronecan
    from dronecan import transport
    m = dronecan.uavcan.equipment.gnss.Fix2()
    m.timestamp.usec, m.status = seeds.T0_US, 3
    m.latitude_deg_1e8, m.longitude_deg_1e8 = 4_739_774_200, 854_559_400
    m.ned_velocity = [5.0, 0.0, 0.0]
    for k, v in values.items():
        setattr(m, k, v)
    return [(f.message_id, bytes(f.bytes)) for f in transport.Transfer(source_node_id=10, payload=m).to_frames()]


def test_can_fix_off_the_globe_is_skipped():
    samples, source = feed(fix2(latitude_deg_1e8=9_100_000_000))
    assert samples == [] and source.stats["gnss_bad_position"] == 1


@pytest.mark.parametrize("vn, counted", [(math.nan, 0), (1e30, 1)])
def test_can_fix_velocity_not_finite_or_too_fast_is_left_out(vn, counted):
    (fix,), source = feed(fix2(ned_velocity=[vn, 0.0, 0.0]))
    assert fix.fix_ok and fix.vel_n_mps is None and fix.vel_e_mps is None
    assert source.stats["bad_value"] == counted


def test_can_magnetometer_not_finite_is_not_attached():
    import dronecan
    from dronecan import transport
    m = dronecan.uavcan.equipment.ahrs.MagneticFieldStrength2()
    m.magnetic_field_ga = [0.2, 0.0, 0.4]
    payload = bytearray(transport.Transfer(source_node_id=11, payload=m).payload)
    at = payload.index(struct.pack("<e", 0.4))
    payload[at:at + 2] = b"\x01\x7e"                    # NaN
    frames = seeds.raw_transfer_frames(MAG2, 11, bytes(payload))
    frames += seeds.raw_transfer_frames(RAW_IMU, 11, bytes(imu_payload()), 1)
    (imu,), source = feed(frames)
    assert source.stats["bad_value"] == 1 and imu.mag_x_gauss is None


def test_a_log_that_is_not_one_is_a_source_error(tmp_path):
    with pytest.raises(SourceError):
        read(b"\xa3\x95\x80" + bytes(200), ".bin", tmp_path)
