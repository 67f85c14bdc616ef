"""Unit conversions at the MAVLink edge (guard.sources.mavlink.to_sample), and sim's encoding against guard's decoding.

Every message here goes through real MAVLink 2 bytes: encoded and packed with pymavlink, then decoded
by a separate pymavlink parser, so the field types are exactly what a link or a tlog delivers.

Tolerances are the wire's quantisation: lat/lon 1e-7 deg, alt and h_acc 1 mm, vel 1 cm/s with cog
0.01 deg, vel_acc 1 mm/s, RAW_IMU 1 mG, 1 mrad/s, 1 mGauss. The simulator rounds to the nearest
step (h_acc and vel_acc it truncates), so a round trip is within half a step (a whole one for those).
"""

import math

import guard.sources.mavlink  # noqa: F401  (sets MAVLINK20=1 before pymavlink is imported)
import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from guard.sources.mavlink import to_sample
from guard.model.samples import Attitude, GnssFix, ImuSample, VehicleType
from guard_sim.mavout import Encoder
from guard_sim.sensors import ImuReading

G = 9.80665


def wire(msg, sender=None):
    """Pack `msg` into MAVLink 2 bytes and decode them with a fresh parser."""
    sender = sender or mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    buf = msg.pack(sender)
    assert buf[0] == 0xFD, "not a MAVLink 2 frame"
    return mavlink.MAVLink(None).decode(bytearray(buf))


def gps(lat=404237000, lon=-869212000, alt=187000, vel=500, cog=0, fix_type=3, h_acc=1500, vel_acc=250, eph=100):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return wire(mav.gps_raw_int_encode(123_456_789, fix_type, lat, lon, alt, eph, 150, vel, cog, 12,
                                       alt_ellipsoid=alt, h_acc=h_acc, v_acc=2000, vel_acc=vel_acc), mav)


def raw_imu(acc=(0, 0, -1000), gyro=(0, 0, 0), mag=(200, -16, 479)):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return wire(mav.raw_imu_encode(5_000_000, *acc, *gyro, *mag), mav)


def attitude(roll=0.0, pitch=0.0, time_boot_ms=2500):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return wire(mav.attitude_encode(time_boot_ms, roll, pitch, 0.3, 0.0, 0.0, 0.0), mav)


# -- GPS_RAW_INT ---------------------------------------------------------------------------------

def test_gps_position_units():
    sample, reason = to_sample(gps(lat=404237123, lon=-869212456, alt=187250))
    assert reason is None
    assert isinstance(sample, GnssFix)
    assert sample.t_us == 123_456_789
    assert sample.fix_ok is True
    assert sample.lat_deg == pytest.approx(40.4237123, abs=1e-12)
    assert sample.lon_deg == pytest.approx(-86.9212456, abs=1e-12)
    assert sample.alt_m == pytest.approx(187.25, abs=1e-12)


@pytest.mark.parametrize("cog_deg, vn, ve", [
    (0.0, 5.0, 0.0),
    (90.0, 0.0, 5.0),
    (225.0, -5.0 / math.sqrt(2), -5.0 / math.sqrt(2)),
])
def test_gps_velocity_from_speed_and_course(cog_deg, vn, ve):
    sample, _ = to_sample(gps(vel=500, cog=int(round(cog_deg * 100))))
    assert sample.vel_n_mps == pytest.approx(vn, abs=1e-9)
    assert sample.vel_e_mps == pytest.approx(ve, abs=1e-9)


def test_gps_accuracies_mm_to_m():
    sample, _ = to_sample(gps(h_acc=1234, vel_acc=56))
    assert sample.h_acc_m == pytest.approx(1.234, abs=1e-12)
    assert sample.vel_acc_mps == pytest.approx(0.056, abs=1e-12)


@pytest.mark.parametrize("eph, hdop", [(100, 1.0), (196, 1.96), (65535, None), (0, None), (9999, None)])
def test_gps_hdop_from_eph(eph, hdop):
    """eph is HDOP x 100; UINT16_MAX is unknown, and 0 or beyond 50 is not a geometry."""
    sample, _ = to_sample(gps(eph=eph))
    assert sample.hdop == (None if hdop is None else pytest.approx(hdop))


def test_gps_accuracy_zero_means_not_sent():
    sample, _ = to_sample(gps(h_acc=0, vel_acc=0))
    assert sample.h_acc_m is None
    assert sample.vel_acc_mps is None


@pytest.mark.parametrize("vel, cog", [(65535, 9000), (500, 65535), (65535, 65535)])
def test_gps_unknown_velocity_or_course_gives_no_velocity(vel, cog):
    sample, reason = to_sample(gps(vel=vel, cog=cog))
    assert reason is None
    assert sample.vel_n_mps is None and sample.vel_e_mps is None
    assert sample.lat_deg == pytest.approx(40.4237, abs=1e-9)     # the position is still there


@pytest.mark.parametrize("fix_type", [0, 1, 2])
def test_gps_without_3d_fix_is_a_sample_with_fix_ok_false(fix_type):
    sample, reason = to_sample(gps(fix_type=fix_type))
    assert reason is None
    assert isinstance(sample, GnssFix)
    assert sample.fix_ok is False


@pytest.mark.parametrize("fix_type", [3, 4, 6])
def test_gps_3d_fix_and_better_are_ok(fix_type):
    assert to_sample(gps(fix_type=fix_type))[0].fix_ok is True


@pytest.mark.parametrize("lat, lon", [(910_000_000, 0), (-900_000_001, 100), (400_000_000, 1_800_000_001),
                                      (0, 0)])
def test_gps_impossible_position_with_a_fix_is_skipped(lat, lon):
    assert to_sample(gps(lat=lat, lon=lon, fix_type=3)) == (None, "gnss_bad_position")


def test_gps_impossible_position_without_a_fix_is_not_an_error():
    sample, reason = to_sample(gps(lat=0, lon=0, fix_type=1))
    assert reason is None
    assert sample.fix_ok is False


# -- RAW_IMU -------------------------------------------------------------------------------------

def test_raw_imu_units():
    sample, reason = to_sample(raw_imu(acc=(1000, -250, -1000), gyro=(1000, -20, 314), mag=(500, -16, 479)))
    assert reason is None
    assert isinstance(sample, ImuSample)
    assert sample.t_us == 5_000_000
    assert (sample.acc_x_mps2, sample.acc_y_mps2, sample.acc_z_mps2) == pytest.approx(
        (9.80665, -0.25 * 9.80665, -9.80665), abs=1e-12)
    assert (sample.gyro_x_radps, sample.gyro_y_radps, sample.gyro_z_radps) == pytest.approx(
        (1.0, -0.020, 0.314), abs=1e-12)
    assert (sample.mag_x_gauss, sample.mag_y_gauss, sample.mag_z_gauss) == pytest.approx(
        (0.5, -0.016, 0.479), abs=1e-12)


def test_raw_imu_all_zero_magnetometer_is_none():
    sample, _ = to_sample(raw_imu(mag=(0, 0, 0)))
    assert (sample.mag_x_gauss, sample.mag_y_gauss, sample.mag_z_gauss) == (None, None, None)
    assert sample.acc_z_mps2 == pytest.approx(-G)


def test_raw_imu_one_zero_magnetometer_axis_is_a_reading():
    sample, _ = to_sample(raw_imu(mag=(0, 0, 450)))
    assert (sample.mag_x_gauss, sample.mag_y_gauss, sample.mag_z_gauss) == pytest.approx((0.0, 0.0, 0.45))


# -- HIGHRES_IMU (PX4) ------------------------------------------------------------------------------

ACC_GYRO, MAG = 0b111111, 0b111 << 6


def highres_imu(acc=(0.0, 0.0, -G), gyro=(0.0, 0.0, 0.0), mag=(0.2, -0.016, 0.479), fields=ACC_GYRO | MAG,
                t_us=5_000_000):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return wire(mav.highres_imu_encode(t_us, *acc, *gyro, *mag, 1013.0, 0.0, 0.0, 25.0, fields), mav)


def test_highres_imu_units_are_si():
    sample, reason = to_sample(highres_imu(acc=(9.8, -2.5, -9.7), gyro=(1.0, -0.02, 0.314), mag=(0.5, -0.016, 0.479)))
    assert reason is None
    assert isinstance(sample, ImuSample)
    assert sample.t_us == 5_000_000
    assert (sample.acc_x_mps2, sample.acc_y_mps2, sample.acc_z_mps2) == pytest.approx((9.8, -2.5, -9.7), rel=1e-6)
    assert (sample.gyro_x_radps, sample.gyro_y_radps, sample.gyro_z_radps) == pytest.approx((1.0, -0.02, 0.314),
                                                                                          rel=1e-6)
    assert (sample.mag_x_gauss, sample.mag_y_gauss, sample.mag_z_gauss) == pytest.approx((0.5, -0.016, 0.479), rel=1e-6)


def test_highres_imu_magnetometer_not_marked_new_is_not_a_reading():
    """PX4 sends its last magnetometer reading with every IMU sample and marks a new one in fields_updated."""
    sample, reason = to_sample(highres_imu(fields=ACC_GYRO))
    assert reason is None
    assert (sample.mag_x_gauss, sample.mag_y_gauss, sample.mag_z_gauss) == (None, None, None)
    assert sample.acc_z_mps2 == pytest.approx(-G, rel=1e-6)


def test_highres_imu_without_fields_updated_is_taken_at_its_values():
    sample, _ = to_sample(highres_imu(fields=0))
    assert sample.mag_z_gauss == pytest.approx(0.479, rel=1e-6)
    sample, _ = to_sample(highres_imu(fields=0, mag=(0.0, 0.0, 0.0)))
    assert sample.mag_x_gauss is None


def test_highres_imu_without_a_new_accelerometer_or_gyro_is_skipped():
    assert to_sample(highres_imu(fields=MAG | 0b000111)) == (None, "imu_not_new")


@pytest.mark.parametrize("acc, gyro", [((math.nan, 0.0, -G), (0.0, 0.0, 0.0)), ((0.0, 0.0, -G), (0.0, math.inf, 0.0))])
def test_highres_imu_non_finite_is_skipped(acc, gyro):
    assert to_sample(highres_imu(acc=acc, gyro=gyro)) == (None, "imu_invalid")


@pytest.mark.parametrize("acc, gyro", [((1e30, 0.0, -G), (0.0, 0.0, 0.0)), ((0.0, 0.0, -G), (0.0, 0.0, -40.0))])
def test_highres_imu_beyond_any_sensors_range_is_skipped(acc, gyro):
    """One corrupt or hostile float would make the filter diverge: beyond RAW_IMU's own range, skipped."""
    assert to_sample(highres_imu(acc=acc, gyro=gyro)) == (None, "imu_out_of_range")
    sample, reason = to_sample(highres_imu(mag=(0.2, 1e9, 0.4)))
    assert reason is None and sample.mag_x_gauss is None


def test_highres_imu_non_finite_magnetometer_is_no_reading():
    sample, reason = to_sample(highres_imu(mag=(math.nan, 0.1, 0.4)))
    assert reason is None and sample.mag_x_gauss is None and sample.acc_z_mps2 == pytest.approx(-G, rel=1e-6)


def test_highres_imu_time_past_any_clock_is_skipped():
    assert to_sample(highres_imu(t_us=2**63))[1] == "time_implausible"


def test_sim_as_px4_sends_the_same_reading_as_highres_imu():
    """The simulator's PX4 output carries RAW_IMU's numbers in SI floats: the two decode alike."""
    rng = np.random.default_rng(11)
    raw_enc, px4_enc = Encoder(), Encoder("px4")
    decoder = mavlink.MAVLink(None)
    for i in range(50):
        reading = ImuReading(tuple(rng.normal(0.0, 5.0, 3) + (0.0, 0.0, -G)), tuple(rng.normal(0.0, 1.0, 3)),
                             tuple(rng.normal(0.0, 0.4, 3)))
        raw = raw_enc.raw_imu(20_000 * i, reading)
        msg = decoder.decode(bytearray(px4_enc.pack(raw)))
        assert msg.get_type() == "HIGHRES_IMU"
        a, b = to_sample(raw)[0], to_sample(msg)[0]
        for field in ("t_us", "acc_x_mps2", "acc_y_mps2", "acc_z_mps2", "gyro_x_radps", "gyro_y_radps",
                      "gyro_z_radps", "mag_x_gauss", "mag_y_gauss", "mag_z_gauss"):
            assert getattr(b, field) == pytest.approx(getattr(a, field), rel=1e-6, abs=1e-9), field


def test_one_imu_stream_is_read_and_the_other_said_once():
    from guard.sources.mavlink import ImuStream
    said: list[str] = []
    stream = ImuStream(said.append)
    assert [stream(k) for k in ("HIGHRES_IMU", "RAW_IMU", "HIGHRES_IMU", "RAW_IMU")] == [True, False, True, False]
    assert len(said) == 1 and "RAW_IMU is sent too" in said[0] and "HIGHRES_IMU" in said[0]


# -- ATTITUDE and others ---------------------------------------------------------------------------

def test_attitude_units():
    sample, reason = to_sample(attitude(roll=0.1, pitch=-0.2, time_boot_ms=2500))
    assert reason is None
    assert isinstance(sample, Attitude)
    assert sample.t_us == 2_500_000
    assert sample.roll_rad == pytest.approx(0.1, abs=1e-7)      # float32 on the wire
    assert sample.pitch_rad == pytest.approx(-0.2, abs=1e-7)


@pytest.mark.parametrize("roll, pitch", [(math.nan, 0.0), (0.0, math.nan), (math.inf, 0.0)])
def test_attitude_non_finite_is_skipped(roll, pitch):
    msg = attitude(roll=roll, pitch=pitch)
    assert not (math.isfinite(msg.roll) and math.isfinite(msg.pitch))      # it really crossed the wire
    assert to_sample(msg) == (None, "attitude_non_finite")


def test_unused_message_is_neither_sample_nor_skip():
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = wire(mav.system_time_encode(1_700_000_000_000_000, 1000), mav)
    assert to_sample(msg) == (None, None)


@pytest.mark.parametrize("mav_type, autopilot, expected", [
    (mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, VehicleType(True)),
    (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, VehicleType(False)),
    (mavlink.MAV_TYPE_SURFACE_BOAT, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, VehicleType(False)),   # drifts sideways
    (mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, None),                # a ground station: not the vehicle
    (mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_INVALID, None),       # a companion on a rover: not it
])
def test_heartbeat_gives_the_vehicle_class_of_autopilots_only(mav_type, autopilot, expected):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = wire(mav.heartbeat_encode(mav_type, autopilot, 0, 0, 4), mav)
    assert to_sample(msg) == (expected, None)


# -- the simulator's encoder against guard's decoder ---------------------------------------------

def sim_wire(make):
    """Encode with the simulator's Encoder, serialise with its sequence numbering, decode fresh."""
    enc = Encoder()
    buf = enc.pack(make(enc))
    assert buf[0] == 0xFD
    return mavlink.MAVLink(None).decode(bytearray(buf))


def test_sim_gps_round_trip():
    rng = np.random.default_rng(20240611)
    cases = [(0.0, 0.0), (5.0, 0.0), (0.0, 5.0), (-3.0, -3.0), (1e-4, -1e-4), (12.34, -0.001), (-0.004, 7.0)]
    cases += [tuple(v) for v in rng.uniform(-15.0, 15.0, (30, 2))]
    for i, (vn, ve) in enumerate(cases):
        lat = float(rng.uniform(-89.0, 89.0))
        lon = float(rng.uniform(-179.0, 179.0))
        alt = float(rng.uniform(-100.0, 3000.0))
        h_acc = float(rng.uniform(0.3, 9.0))
        vel_acc = float(rng.uniform(0.01, 0.5))
        t_us = 100_000 * i
        msg = sim_wire(lambda enc: enc.gps_raw_int(t_us, lat, lon, alt, vn, ve, h_acc, vel_acc))
        sample, reason = to_sample(msg)
        assert reason is None, (i, reason)
        assert sample.t_us == t_us
        assert sample.fix_ok
        assert sample.lat_deg == pytest.approx(lat, abs=0.5e-7 + 1e-12)
        assert sample.lon_deg == pytest.approx(lon, abs=0.5e-7 + 1e-12)
        assert sample.alt_m == pytest.approx(alt, abs=0.5e-3 + 1e-9)
        # speed to the nearest cm/s, course to the nearest 0.01 deg: error <= 0.005 + speed * 8.7e-5 m/s
        bound = 0.005 + math.hypot(vn, ve) * math.radians(0.005) + 1e-9
        assert math.hypot(sample.vel_n_mps - vn, sample.vel_e_mps - ve) <= bound, (i, vn, ve, sample)
        assert abs(sample.vel_n_mps - vn) <= 0.01 and abs(sample.vel_e_mps - ve) <= 0.01
        assert abs(h_acc - sample.h_acc_m) <= 0.5e-3 + 1e-9           # rounded to whole mm
        assert abs(vel_acc - sample.vel_acc_mps) <= 0.5e-3 + 1e-9


def test_sim_gps_fix_type_round_trip():
    msg = sim_wire(lambda enc: enc.gps_raw_int(0, 40.0, -86.0, 187.0, 1.0, 1.0, 1.5, 0.05, fix_type=1))
    sample, reason = to_sample(msg)
    assert reason is None and sample.fix_ok is False


def test_sim_imu_round_trip():
    rng = np.random.default_rng(7)
    for i in range(50):
        acc = tuple(float(a) for a in rng.normal(0.0, 5.0, 3) + (0.0, 0.0, -G))
        gyro = tuple(float(w) for w in rng.normal(0.0, 1.0, 3))
        mag = tuple(float(m) for m in rng.normal(0.0, 0.4, 3))
        t_us = 20_000 * i
        msg = sim_wire(lambda enc: enc.raw_imu(t_us, ImuReading(acc, gyro, mag)))
        sample, reason = to_sample(msg)
        assert reason is None
        assert sample.t_us == t_us
        got_acc = (sample.acc_x_mps2, sample.acc_y_mps2, sample.acc_z_mps2)
        got_gyro = (sample.gyro_x_radps, sample.gyro_y_radps, sample.gyro_z_radps)
        got_mag = (sample.mag_x_gauss, sample.mag_y_gauss, sample.mag_z_gauss)
        assert got_acc == pytest.approx(acc, abs=0.5e-3 * G + 1e-12)      # half a mG
        assert got_gyro == pytest.approx(gyro, abs=0.5e-3 + 1e-12)        # half a mrad/s
        assert got_mag == pytest.approx(mag, abs=0.5e-3 + 1e-12)          # half a mGauss


def test_sim_imu_at_rest_reads_minus_one_g():
    level = ImuReading((0.0, 0.0, -G), (0.0, 0.0, 0.0), (0.2, -0.016, 0.479))
    msg = sim_wire(lambda enc: enc.raw_imu(0, level))
    assert (msg.xacc, msg.yacc, msg.zacc) == (0, 0, -1000)
    assert to_sample(msg)[0].acc_z_mps2 == pytest.approx(-G, abs=1e-12)


def _imu(t_us, mag):
    from guard.model.samples import ImuSample
    return ImuSample(t_us, 0.0, 0.0, -9.8, 0.0, 0.0, 0.0, *mag)


def test_a_slower_compasss_reading_sent_again_and_again_counts_once():
    """RAW_IMU at 50 Hz carrying a 10 Hz compass: each reading five times. Once the compass's period is
    learnt, the four repeats go on without it; a reading that changes is taken at once; a noiseless
    compass reading the same value a period later (ArduPilot's SITL) is a new reading; a compass as
    fast as the stream loses nothing; a reboot's time going back takes the next reading."""
    from guard.sources.mavlink import CompassRepeats
    rng = np.random.default_rng(0)
    repeats, kept = CompassRepeats(), []
    value = None
    for k in range(500):
        if k % 5 == 0:
            value = tuple(float(v) for v in rng.normal(0.2, 0.01, 3))
        kept.append(repeats(_imu(k * 20_000, value)).mag_x_gauss is not None)
    assert repeats.period_us == 100_000
    after = kept[200:]
    assert sum(after) == len(after) // 5 and all(after[i] for i in range(0, len(after), 5)), after[:12]
    # the same value a period later: a new reading (a noiseless compass)
    assert repeats(_imu(500 * 20_000, value)).mag_x_gauss is not None
    assert repeats(_imu(501 * 20_000, value)).mag_x_gauss is None
    assert repeats(_imu(505 * 20_000, value)).mag_x_gauss is not None
    assert repeats(_imu(1_000, value)).mag_x_gauss is not None                 # time went back: a reboot
    fast = CompassRepeats()
    got = [fast(_imu(k * 20_000, tuple(float(v) for v in rng.normal(0.2, 0.01, 3)))).mag_x_gauss for k in range(300)]
    assert None not in got and fast.period_us == 20_000


@pytest.mark.parametrize("imu_hz, mag_hz", [(50, 10), (50, 20), (50, 40), (25, 20), (100, 75), (200, 75),
                                            (400, 75), (400, 10), (100, 100), (30, 30)])
def test_a_compass_slower_than_the_stream_is_read_once_per_reading_whatever_the_two_rates(imu_hz, mag_hz):
    """Readings at k / mag_hz, each taken by the first RAW_IMU at or after it (times on the stream's
    microseconds), held until the next: after the period is learnt, guard reads each reading once,
    even where the compass is a little slower than the stream (75 Hz in 100 Hz: changes one or two
    samples apart, whose median gap is the stream's period, not the compass's)."""
    from guard.sources.mavlink import CompassRepeats
    rng = np.random.default_rng(imu_hz * 1000 + mag_hz)
    repeats, value, j = CompassRepeats(), None, 0
    new, kept = [], []
    for k in range(imu_hz * 20):
        t_us = round(k * 1e6 / imu_hz)
        if t_us >= round(j * 1e6 / mag_hz):
            value = tuple(float(v) for v in rng.normal(0.2, 0.01, 3))
            new.append(t_us)
            while round(j * 1e6 / mag_hz) <= t_us:
                j += 1
        if repeats(_imu(t_us, value)).mag_x_gauss is not None:
            kept.append(t_us)
    assert repeats.period_us == pytest.approx(1e6 / min(mag_hz, imu_hz), rel=0.15)
    learnt = new[CompassRepeats.PERIOD_CHANGES]
    assert [t for t in kept if t > learnt] == [t for t in new if t > learnt]
