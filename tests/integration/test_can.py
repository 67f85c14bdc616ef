"""CAN source: simulator publisher -> python-can virtual bus -> CanSource, frames only between them.

Tolerances. DroneCAN sends lat/lon as integer 1e-8 deg, heights as integer mm, Fix2.ned_velocity as
float32, and RawIMU's latest accelerometer and gyro samples and the magnetometer as float16 (11-bit
significand): a float16 value is within a relative 2**-11 (about 4.9e-4) of what was sent, e.g.
±0.0039 m/s^2 at 9.81 m/s^2. The tests compare with the very rounding (struct's 'e' and 'f').
"""

import errno
import logging
import os
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import dronecan
import pytest

from guard.sources.can import FIX2, MAG2, RAW_IMU, CanSource, parse_can_url
from guard.errors import ConfigError, SourceError
from guard.model.samples import GnssFix, ImuSample
from guard_sim.canbus import CanPublisher

GNSS = dict(lat_deg=47.397742123, lon_deg=8.545594456, alt_m=488.123, vel_n=1.1, vel_e=-2.2, vel_d=0.3,
            fix3d=True, h_acc_m=1.5)


def f16(x: float) -> float:
    return struct.unpack("<e", struct.pack("<e", x))[0]


def f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


@pytest.fixture
def url():
    return f"can:virtual:test-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def pair(url):
    """(source, publisher) on one fresh virtual channel; the source's bus opens first."""
    source = CanSource(url, gnss_node_id=10, imu_node_id=11)
    publisher = CanPublisher(url, gnss_node_id=10, imu_node_id=11)
    yield source, publisher
    publisher.close()
    source.close()


def read(source: CanSource, messages: list) -> list:
    """Poll once per frame sent (each poll consumes one frame); the samples they completed."""
    out = [source.poll(1.0) for _ in messages]
    return [s for s in out if s is not None]


def send_read(source, publisher, messages):
    publisher.send(messages)
    return read(source, messages)


def test_parse_can_url():
    assert parse_can_url("can:socketcan:can0") == ("socketcan", "can0")
    assert parse_can_url("can:virtual:bus0") == ("virtual", "bus0")
    assert parse_can_url("can:udp_multicast:239.74.163.2") == ("udp_multicast", "239.74.163.2")
    assert parse_can_url("can:udp_multicast:ff15:7079::1") == ("udp_multicast", "ff15:7079::1")
    for bad in ("can:socketcan", "can::can0", "can:socketcan:", "udpin:0.0.0.0:14550", "can0"):
        with pytest.raises(ConfigError, match=bad):
            parse_can_url(bad)


def test_data_type_ids_are_dronecan_s():
    eq = dronecan.uavcan.equipment
    assert (FIX2, RAW_IMU, MAG2) == (eq.gnss.Fix2.default_dtid, eq.ahrs.RawIMU.default_dtid,
                                     eq.ahrs.MagneticFieldStrength2.default_dtid)


def test_round_trip_units(pair):
    source, pub = pair
    acc, gyro, mag = (0.1234, -0.5, -9.80665), (0.001, 0.3333, -1.2345), (0.21, -0.047, 0.43)
    gnss = pub.encode_gnss(1_000_000, **GNSS)
    assert len(gnss) > 1                                  # Fix2 is a multi-frame transfer (with CRC)
    imu1 = pub.encode_imu(1_010_000, acc, gyro)
    mag_msgs = pub.encode_mag(1_015_000, mag)
    imu2 = pub.encode_imu(1_020_000, acc, gyro)
    imu3 = pub.encode_imu(1_030_000, acc, gyro)
    fix, first, second, third = send_read(source, pub, gnss + imu1 + mag_msgs + imu2 + imu3)

    assert isinstance(fix, GnssFix) and fix.fix_ok and fix.t_us == 1_000_000
    assert fix.lat_deg == round(GNSS["lat_deg"] * 1e8) / 1e8           # integer 1e-8 deg
    assert fix.lon_deg == round(GNSS["lon_deg"] * 1e8) / 1e8
    assert abs(fix.lat_deg - GNSS["lat_deg"]) < 1e-7 and abs(fix.lon_deg - GNSS["lon_deg"]) < 1e-7
    assert fix.alt_m == pytest.approx(488.123, abs=0.0005)               # integer mm
    assert (fix.vel_n_mps, fix.vel_e_mps) == (f32(1.1), f32(-2.2))       # float32
    assert fix.h_acc_m == pytest.approx(1.5, rel=2**-11)                 # sqrt of a float16 variance
    assert fix.vel_acc_mps is None                                       # sent as NaN: unknown

    assert isinstance(first, ImuSample) and first.t_us == 1_010_000
    got_acc = (first.acc_x_mps2, first.acc_y_mps2, first.acc_z_mps2)
    got_gyro = (first.gyro_x_radps, first.gyro_y_radps, first.gyro_z_radps)
    assert got_acc == tuple(f16(a) for a in acc) and got_gyro == tuple(f16(g) for g in gyro)
    assert got_acc == pytest.approx(acc, rel=2**-11) and got_gyro == pytest.approx(gyro, rel=2**-11)
    assert (first.mag_x_gauss, first.mag_y_gauss, first.mag_z_gauss) == (None, None, None)
    assert second.t_us == 1_020_000
    assert (second.mag_x_gauss, second.mag_y_gauss, second.mag_z_gauss) == tuple(f16(m) for m in mag)
    # one reading, one measurement: the next IMU sample does not carry it again
    assert (third.mag_x_gauss, third.mag_y_gauss, third.mag_z_gauss) == (None, None, None)
    assert source.messages == {"uavcan.equipment.gnss.Fix2": 1, "uavcan.equipment.ahrs.RawIMU": 3,
                               "uavcan.equipment.ahrs.MagneticFieldStrength2": 1}
    assert sum(source.stats.values()) == 0


def test_transfer_ids_wrap_per_type_and_node(pair):
    source, pub = pair
    samples = []
    for k in range(40):                                   # beyond the 5-bit transfer id
        samples += send_read(source, pub, pub.encode_gnss(k * 100_000 + 1, **GNSS)
                             + pub.encode_imu(k * 100_000 + 2, (0, 0, -9.8), (0, 0, 0)))
    assert [s.t_us for s in samples] == [k * 100_000 + d for k in range(40) for d in (1, 2)]
    assert source.stats["bad_transfer"] == 0


def test_no_fix_is_counted_and_passed_on(pair):
    source, pub = pair
    (fix,) = send_read(source, pub, pub.encode_gnss(5, **{**GNSS, "fix3d": False}))
    assert not fix.fix_ok and source.stats["no_fix"] == 1


def test_other_nodes_are_ignored_and_counted(pair, url):
    source, pub = pair
    with CanPublisher(url, gnss_node_id=12, imu_node_id=13) as other:
        foreign = other.encode_gnss(1, **GNSS) + other.encode_imu(2, (0, 0, -9.8), (0, 0, 0)) \
            + other.encode_mag(3, (0.2, 0.0, 0.4))
        other.send(foreign)
        assert read(source, foreign) == []
    assert source.stats["other_node"] == 3                 # once per transfer, not per frame
    (imu,) = send_read(source, pub, pub.encode_imu(4, (0, 0, -9.8), (0, 0, 0)))
    assert imu.mag_x_gauss is None                         # the other node's magnetometer was not taken


def test_unset_node_id_locks_onto_first_node(url):
    with CanSource(url, gnss_node_id=None, imu_node_id=None) as source, \
            CanPublisher(url, gnss_node_id=21, imu_node_id=22) as first, \
            CanPublisher(url, gnss_node_id=31, imu_node_id=32) as second:
        msgs = first.encode_gnss(1, **GNSS)
        first.send(msgs)
        assert len(read(source, msgs)) == 1
        msgs = second.encode_gnss(2, **GNSS)
        second.send(msgs)
        assert read(source, msgs) == [] and source.stats["other_node"] == 1
        assert source.node == {"gnss": 21, "imu": None}


def test_unknown_types_service_and_non_dronecan_frames(pair):
    source, pub = pair
    status = dronecan.uavcan.protocol.NodeStatus(uptime_sec=5)
    frames = dronecan.transport.Transfer(transfer_id=0, source_node_id=10, payload=status).to_frames()
    msgs = [can.Message(arbitration_id=f.message_id, data=bytes(f.bytes)) for f in frames]
    msgs.append(can.Message(arbitration_id=(31 << 24) | (20000 << 8) | 10, data=b"\x01\xc0"))   # no such type
    msgs.append(can.Message(arbitration_id=(31 << 24) | (1 << 16) | (1 << 15) | (11 << 8) | 0x80 | 10,
                            data=b"\x00\xc0"))                                                  # service request
    msgs.append(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"))    # 11-bit
    assert send_read(source, pub, msgs) == []
    assert source.stats["unknown_type"] == 3 and source.stats["not_dronecan"] == 1


def _next_fix_still_decodes(source, pub, t_us=9_000_000):
    (fix,) = send_read(source, pub, pub.encode_gnss(t_us, **GNSS))
    assert fix.t_us == t_us


def test_cut_off_transfer_is_counted(pair):
    source, pub = pair
    msgs = pub.encode_gnss(1, **GNSS)
    assert send_read(source, pub, msgs[:3]) == []
    _next_fix_still_decodes(source, pub)
    assert source.stats["bad_transfer"] == 1


def test_cut_off_transfer_then_silence_is_counted(url):
    with CanSource(url, gnss_node_id=10, imu_node_id=11, timeout_s=0.2) as source, CanPublisher(url) as pub:
        assert send_read(source, pub, pub.encode_gnss(1, **GNSS)[:3]) == []
        assert source.poll(0.0) is None and source.stats["bad_transfer"] == 0   # may still come
        assert source.poll(0.3) is None                    # no frame for timeout_s: dropped
        assert source.stats["bad_transfer"] == 1
        _next_fix_still_decodes(source, pub)
        assert source.stats["bad_transfer"] == 1


def test_importing_guard_can_imports_no_can_library():
    code = "import sys, guard.sources.can; assert not {'can', 'dronecan'} & set(sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[2])


def test_out_of_order_frames_are_counted(pair):
    source, pub = pair
    msgs = pub.encode_gnss(1, **GNSS)
    msgs[1], msgs[2] = msgs[2], msgs[1]
    assert send_read(source, pub, msgs) == []
    assert source.stats["bad_transfer"] == 1
    _next_fix_still_decodes(source, pub)


def test_frames_without_their_start_are_counted_once(pair):
    source, pub = pair
    assert send_read(source, pub, pub.encode_gnss(1, **GNSS)[1:]) == []
    assert source.stats["bad_transfer"] == 1
    _next_fix_still_decodes(source, pub)


def test_wrong_transfer_crc_is_counted(pair, caplog):
    source, pub = pair
    caplog.set_level(logging.DEBUG, logger="guard.sources.can")
    msgs = pub.encode_gnss(1, **GNSS)
    data = bytearray(msgs[2].data)
    data[0] ^= 0x5A                                        # a payload byte, not the tail byte
    msgs[2].data = data
    assert send_read(source, pub, msgs) == []
    assert source.stats["bad_transfer"] == 1
    assert "CRC mismatch" in caplog.text
    _next_fix_still_decodes(source, pub)


def test_missing_timestamp_is_skipped_or_taken_from_reception(url, caplog):
    with CanSource(url, gnss_node_id=10, imu_node_id=11) as by_msg, \
            CanSource(url, gnss_node_id=10, imu_node_id=11, time_source="receive") as by_rx, \
            CanPublisher(url) as pub:
        msgs = pub.encode_imu(0, (0, 0, -9.8), (0, 0, 0)) * 2
        pub.send(msgs)
        before = time.time()
        assert read(by_msg, msgs) == [] and by_msg.stats["no_timestamp"] == 2
        assert caplog.text.count("has no timestamp") == 1
        samples = read(by_rx, msgs)
        assert len(samples) == 2 and abs(samples[0].t_us / 1e6 - before) < 5.0


def test_silence_warns_once_and_keeps_waiting(url, caplog):
    caplog.set_level(logging.INFO, logger="guard.sources.can")
    source = CanSource(url, gnss_node_id=10, imu_node_id=11, timeout_s=0.1)
    pub = CanPublisher(url)
    got = []

    def consume():
        for sample in source.samples():
            got.append(sample)

    reader = threading.Thread(target=consume, daemon=True)
    reader.start()
    pub.send_gnss(1, **GNSS)
    time.sleep(0.6)                                        # several timeouts without a frame
    assert reader.is_alive() and len(got) == 1
    gnss_warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "no GNSS" in r.message]
    assert len(gnss_warnings) == 1 and "node 10" in gnss_warnings[0].message
    assert source.stats["silent"] == 2                     # GNSS, and the IMU that never spoke
    pub.send_gnss(2, **GNSS)
    deadline = time.monotonic() + 2.0
    while len(got) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [s.t_us for s in got] == [1, 2] and "GNSS from node 10 again" in caplog.text
    source.close()                                         # stop flag: the generator ends
    reader.join(2.0)
    assert not reader.is_alive()
    pub.close()


def test_bogus_interface_raises_source_error():
    with pytest.raises(SourceError, match="cannot open CAN bus nosuchiface:chan7: "):
        CanSource("can:nosuchiface:chan7", gnss_node_id=10, imu_node_id=11)


def test_socketcan_config_reaches_the_kernel():
    """can:socketcan:vcan0 goes all the way to opening a CAN socket; this kernel has no CAN."""
    if os.path.exists("/sys/class/net/vcan0"):
        pytest.skip("this machine has a vcan0")
    with pytest.raises(SourceError, match="cannot open CAN bus socketcan:vcan0: ") as info:
        CanSource("can:socketcan:vcan0", gnss_node_id=10, imu_node_id=11, bus_kwargs={"fd": False})
    cause = info.value.__cause__
    assert isinstance(cause, OSError) and cause.errno in (errno.EAFNOSUPPORT, errno.ENODEV)
    assert "\n" not in str(info.value)


def test_bad_settings_are_config_errors():
    for kwargs in (dict(gnss_node_id=0, imu_node_id=11), dict(gnss_node_id=10, imu_node_id=128),
                   dict(gnss_node_id=10, imu_node_id=11, timeout_s=0),
                   dict(gnss_node_id=10, imu_node_id=11, time_source="wall")):
        with pytest.raises(ConfigError):
            CanSource("can:virtual:unused", **kwargs)
