"""The simulator's vehicles whose sensors differ from the defaults (sim.scenario.Noise's per-vehicle keys).

Each knob is compared with a run of the same scenario and seed without it. The knobs act on the
sensor model only, after the vehicle has moved (the vehicle steers on GNSS, which none of the IMU
knobs touch, and every error is drawn from the same seeded streams), so a run with a knob differs
from the base run in exactly the fields the knob acts on, and by the amount it should.
Angles: compass heading chi = atan2(-m_y, m_x) (clockwise from north, as guard.core.aiding.imu's
`heading` takes it); `mag_offset_deg` > 0 turns it east. A sensor yawed by a reads (x cos a + y sin a,
-x sin a + y cos a) of a body vector, so `imu_yaw_mount_deg` = a moves a forward acceleration f into
y as -f sin a.
"""

import math
import time
import tomllib
import uuid

import numpy as np
import pymap3d
import pytest
from pymavlink import mavutil
from pyulog import ULog

from guard.core.aiding.imu import heading
from guard.sources import open_log
from guard.sources.can import CanSource
from integration.test_sim import read_tlog
from guard_sim import scenario as scn
from guard_sim.canbus import CanPublisher
from guard_sim.run import Simulation, run
from guard_sim.scenario import SCENARIO_DIR, Noise, ScenarioError
from guard_sim.sensors import earth_field_ned_gauss

SEED = 7
# 30 s around a loop: speeds up from rest, changes speed and turns both ways
BASE = {"name": "vehicles", "duration_s": 30.0, "start": {"heading_deg": 90.0},
        "route": {"waypoints_m": [[0.0, 0.0, 4.0], [60.0, 0.0, 6.0], [80.0, 30.0, 3.0], [40.0, 60.0, 5.0],
                                  [0.0, 40.0, 4.0]], "loop": True, "lookahead_m": 8.0},
        "rates": {"imu_hz": 50.0, "gnss_hz": 10.0}}
# no IMU noise or bias: readings are the true values (and the knobs' effect) to the message's integer
NOISELESS = {"accel_white_mps2": 0.0, "accel_bias_mps2": 0.0, "gyro_white_radps": 0.0, "gyro_bias_radps": 0.0,
             "mag_white_gauss": 0.0}
NEW_KEYS = {"mag_offset_deg": 0.0, "mag_wander_deg": 0.0, "mag_wander_tau_s": 3.0, "mag_iron_x": 0.0,
            "mag_iron_y": 0.0, "accel_scale": 0.0, "gyro_scale": 0.0, "imu_yaw_mount_deg": 0.0,
            "gnss_h_acc_reported": True, "gnss_vel_acc_reported": True, "gnss_course_hold_mps": 0.0,
            "mag_hz": 0.0}


def scenario_with(**noise) -> scn.Scenario:
    return scn.parse({**BASE, "noise": noise}, "vehicles.toml")



def fields(m) -> dict:
    return {k: v for k, v in m.to_dict().items() if k != "mavpackettype"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """simulate(**noise) -> (messages, truth) of BASE with those noise keys, seed SEED; each run once."""
    cache = {}

    def simulate(**noise):
        key = tuple(sorted(noise.items()))
        if key not in cache:
            path = tmp_path_factory.mktemp("vehicles") / "run.tlog"
            truth = run(scenario_with(**noise), SEED, tlog=str(path))
            cache[key] = (read_tlog(path), truth)
        return cache[key]
    return simulate


def raw_imu(msgs, *names) -> np.ndarray:
    """Columns of RAW_IMU (integers as sent: mG, mrad/s, mGauss)."""
    return np.array([[getattr(m, n) for n in names] for m in msgs if m.get_type() == "RAW_IMU"], dtype=float)


def changed_fields(base, other) -> set[tuple[str, str]]:
    """(message, field) pairs that differ between two runs with the same messages at the same times."""
    assert [(m.get_type(), getattr(m, "time_usec", None)) for m in base] == \
        [(m.get_type(), getattr(m, "time_usec", None)) for m in other]
    changed = set()
    for a, b in zip(base, other):
        fa, fb = fields(a), fields(b)
        changed |= {(a.get_type(), k) for k in fa if fa[k] != fb[k]}
    return changed


def compass_deg(msgs) -> np.ndarray:
    """Compass heading chi = atan2(-m_y, m_x) of every RAW_IMU (the vehicle is level), degrees."""
    mxy = raw_imu(msgs, "xmag", "ymag")
    return np.degrees(np.arctan2(-mxy[:, 1], mxy[:, 0]))


def wrap_deg(x):
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


# -- each knob changes what it should and nothing else ---------------------------------------------

@pytest.mark.parametrize("knob, value, expected", [
    ("mag_offset_deg", 5.0, {("RAW_IMU", "xmag"), ("RAW_IMU", "ymag")}),
    ("mag_wander_deg", 3.0, {("RAW_IMU", "xmag"), ("RAW_IMU", "ymag")}),
    ("mag_iron_x", 0.2, {("RAW_IMU", "xmag")}),               # fixed to the body: forward only
    ("accel_scale", 0.1, {("RAW_IMU", "xacc"), ("RAW_IMU", "yacc"), ("RAW_IMU", "zacc")}),
    ("gyro_scale", 0.1, {("RAW_IMU", "zgyro")}),            # a level vehicle turns about z only
    ("imu_yaw_mount_deg", 10.0, {("RAW_IMU", "xacc"), ("RAW_IMU", "yacc")}),
    ("gnss_vel_acc_reported", False, {("GPS_RAW_INT", "vel_acc")}),
    ("gnss_h_acc_reported", False, {("GPS_RAW_INT", "h_acc"), ("GPS_RAW_INT", "v_acc")}),
    ("gnss_course_hold_mps", 4.5, {("GPS_RAW_INT", "cog")}),  # the speed kept, its course held
])
def test_a_knob_changes_only_its_fields(runs, knob, value, expected):
    base, _ = runs()
    other, truth = runs(**{knob: value})
    assert changed_fields(base, other) == expected
    assert truth["noise"][knob] == value                     # the truth file lists it


def test_defaults_are_byte_identical_to_a_scenario_without_the_keys(tmp_path):
    """A shipped scenario, and a copy of it with every new key written out at its default."""
    text = (SCENARIO_DIR / "paper.toml").read_text()
    assert not set(NEW_KEYS) & set(tomllib.loads(text).get("noise", {}))
    lines = "".join(f"{k} = {str(v).lower()}\n" for k, v in NEW_KEYS.items())
    explicit = text.replace("[noise]\n", "[noise]\n" + lines) if "[noise]\n" in text else text + "\n[noise]\n" + lines
    (tmp_path / "without.toml").write_text(text)
    (tmp_path / "with.toml").write_text(explicit)
    with_keys = scn.load(str(tmp_path / "with.toml"))
    assert {k: getattr(with_keys.noise, k) for k in NEW_KEYS} == NEW_KEYS
    assert with_keys == scn.load(str(tmp_path / "without.toml"))
    a, b = tmp_path / "without.tlog", tmp_path / "with.tlog"
    run(scn.load(str(tmp_path / "without.toml")), 2, tlog=str(a))
    truth = run(with_keys, 2, tlog=str(b))
    assert a.read_bytes() == b.read_bytes()
    assert {k: truth["noise"][k] for k in NEW_KEYS} == NEW_KEYS


def test_defaults_are_the_ideal_sensor():
    n = Noise()
    assert (n.mag_offset_deg, n.accel_scale, n.gyro_scale, n.imu_yaw_mount_deg) == (0.0, 0.0, 0.0, 0.0)
    assert n.gnss_h_acc_reported is True and n.gnss_vel_acc_reported is True


# -- the magnetometer ---------------------------------------------------------------------------------

def test_mag_offset_turns_the_compass_heading_east(runs):
    """+5 deg: the heading from RAW_IMU's field is 5 deg east of the one without (and of the truth)."""
    base, truth = runs()
    other, _ = runs(mag_offset_deg=5.0)
    diff = wrap_deg(compass_deg(other) - compass_deg(base))
    assert diff.mean() == pytest.approx(5.0, abs=0.1)         # noise (~1 deg a sample) averages out
    assert np.percentile(np.abs(diff - 5.0), 95) < 2.5
    # the same against the truth, through guard's own heading (ENU yaw, counter-clockwise): 5 deg less
    st = scenario_with().start
    fn, fe, _ = earth_field_ned_gauss(st.lat_deg, st.lon_deg, st.alt_m, st.year)
    declination = math.atan2(fe, fn)
    imu_t = [m.time_usec for m in other if m.get_type() == "RAW_IMU"]
    at_gnss = [imu_t.index(t) for t in truth["trajectory"]["t_usec"]]       # IMU at 50 Hz, GNSS at 10 Hz
    for msgs, offset in ((base, 0.0), (other, 5.0)):
        mxy = raw_imu(msgs, "xmag", "ymag")[at_gnss]
        yaw = np.array([heading(mx, my, declination) for mx, my in mxy])
        error = wrap_deg(np.degrees(yaw - np.array(truth["trajectory"]["yaw_rad"])))
        assert error.mean() == pytest.approx(-offset, abs=0.3)


def test_mag_wander_is_a_gauss_markov_heading_error(runs):
    """mag_wander_deg = 4 over mag_wander_tau_s = 2: the compass heading parts from the one without by
    about 4 degrees rms, and its error one sample (20 ms) apart is nearly the same, 5 s apart nearly
    unrelated: correlated, where the white noise is not."""
    base, _ = runs(**NOISELESS)
    other, _ = runs(**NOISELESS, mag_wander_deg=4.0, mag_wander_tau_s=2.0)
    e = wrap_deg(compass_deg(other) - compass_deg(base))
    assert 2.5 < np.sqrt(np.mean(e * e)) < 6.0
    corr = lambda lag: np.corrcoef(e[:-lag], e[lag:])[0, 1]      # noqa: E731
    assert corr(1) > 0.95 and abs(corr(250)) < 0.5             # IMU at 50 Hz: 20 ms and 5 s


def test_a_hard_iron_turns_the_compass_by_its_deviation_curve(runs):
    """mag_iron_x, mag_iron_y: a field fixed to the body, a fraction of the horizontal one (forward,
    right), adds to the earth's; the compass's heading is then off by chi_m - chi = atan2(sin chi - d_y,
    cos chi + d_x) - chi, which depends on the heading (up to asin |d|)."""
    base, _ = runs(**NOISELESS)
    other, _ = runs(**NOISELESS, mag_iron_x=0.3, mag_iron_y=-0.2)
    chi = np.radians(compass_deg(base))
    expected = np.degrees(np.arctan2(np.sin(chi) + 0.2, np.cos(chi) + 0.3) - chi)
    diff = wrap_deg(compass_deg(other) - compass_deg(base))
    assert np.abs(wrap_deg(diff - expected)).max() < 0.6
    assert np.ptp(diff) > 30.0                                  # by heading: the loop turns it both ways


def test_mag_offset_noiseless_is_a_rotation_of_the_field(runs):
    base, _ = runs(**NOISELESS)
    other, _ = runs(**NOISELESS, mag_offset_deg=-20.0)
    diff = wrap_deg(compass_deg(other) - compass_deg(base))
    assert np.abs(diff + 20.0).max() < 0.6                      # 1 mGauss in ~200 mGauss horizontal
    b, o = raw_imu(base, "xmag", "ymag", "zmag"), raw_imu(other, "xmag", "ymag", "zmag")
    assert np.abs(np.hypot(o[:, 0], o[:, 1]) - np.hypot(b[:, 0], b[:, 1])).max() <= 1.5
    assert np.array_equal(o[:, 2], b[:, 2])


# -- the IMU --------------------------------------------------------------------------------------------

def test_accel_scale_multiplies_the_specific_force(runs):
    base, _ = runs(**NOISELESS)
    other, _ = runs(**NOISELESS, accel_scale=0.1)
    b, o = raw_imu(base, "xacc", "yacc", "zacc"), raw_imu(other, "xacc", "yacc", "zacc")
    accelerating = np.abs(b[:, 0]) >= 30                      # mG: speeding up and slowing down
    assert accelerating.sum() > 100
    assert np.abs(o[accelerating, 0] - 1.1 * b[accelerating, 0]).max() <= 1.1     # two roundings to 1 mG
    assert np.abs(o - 1.1 * b).max() <= 1.1
    assert set(o[:, 2]) == {-1100.0}                           # -g reads 10 % high too


def test_imu_scales_act_before_bias_and_noise(runs):
    """With large biases and noise on, the scaled run differs from the base by scale * the true value."""
    noisy = {"accel_bias_mps2": 2.0, "gyro_bias_radps": 0.2}
    truth_acc = raw_imu(runs(**NOISELESS)[0], "xacc", "yacc", "zacc")
    truth_rate = raw_imu(runs(**NOISELESS)[0], "zgyro")[:, 0]
    b, o = runs(**noisy)[0], runs(**noisy, accel_scale=-0.1, gyro_scale=0.2)[0]
    acc_diff = raw_imu(o, "xacc", "yacc", "zacc") - raw_imu(b, "xacc", "yacc", "zacc")
    assert np.abs(acc_diff - (-0.1) * truth_acc).max() <= 1.2
    rate_diff = raw_imu(o, "zgyro")[:, 0] - raw_imu(b, "zgyro")[:, 0]
    assert np.abs(rate_diff - 0.2 * truth_rate).max() <= 1.2
    assert np.abs(truth_rate).max() > 300                      # mrad/s: it does turn


def test_gyro_scale_multiplies_the_rate(runs):
    base, _ = runs(**NOISELESS)
    other, _ = runs(**NOISELESS, gyro_scale=-0.05)
    b, o = raw_imu(base, "zgyro")[:, 0], raw_imu(other, "zgyro")[:, 0]
    turning = np.abs(b) >= 100
    assert turning.sum() > 100
    assert np.abs(o - 0.95 * b).max() <= 1.0


def test_imu_mount_rotates_x_and_y(runs):
    """Mounted yawed +10 deg: (x, y) reads (x cos a + y sin a, -x sin a + y cos a); forward acceleration
    moves into -y by sin(a); z, the gyro and the compass do not change."""
    a = math.radians(10.0)
    base, _ = runs(**NOISELESS)
    other, _ = runs(**NOISELESS, imu_yaw_mount_deg=10.0)
    names = ("xacc", "yacc", "zacc", "zgyro", "xmag", "ymag", "zmag")
    b, o = raw_imu(base, *names), raw_imu(other, *names)
    x, y = b[:, 0], b[:, 1]
    assert np.abs(o[:, 0] - (x * math.cos(a) + y * math.sin(a))).max() <= 1.1
    assert np.abs(o[:, 1] - (-x * math.sin(a) + y * math.cos(a))).max() <= 1.1
    straight = (np.abs(y) <= 1) & (np.abs(x) >= 30)          # speeding up or slowing down, not turning
    assert straight.sum() > 50
    ratio = o[straight, 1] / x[straight]
    assert ratio.mean() == pytest.approx(-math.sin(a), abs=0.01)
    assert np.array_equal(o[:, 2:], b[:, 2:])


# -- GNSS accuracies ------------------------------------------------------------------------------------

def test_reported_accuracies_follow_the_noise_or_are_zero(runs):
    gps = [m for m in runs()[0] if m.get_type() == "GPS_RAW_INT"]
    assert {(m.h_acc, m.v_acc, m.vel_acc) for m in gps} == {(800, 1200, 50)}       # gnss_h_acc_m, 0.05 m/s
    gps = [m for m in runs(gnss_vel_white_mps=0.2)[0] if m.get_type() == "GPS_RAW_INT"]
    assert {m.vel_acc for m in gps} == {200}                  # vel_acc follows gnss_vel_white_mps
    gps = [m for m in runs(gnss_vel_acc_reported=False)[0] if m.get_type() == "GPS_RAW_INT"]
    assert {(m.h_acc, m.v_acc, m.vel_acc) for m in gps} == {(800, 1200, 0)}
    gps = [m for m in runs(gnss_h_acc_reported=False)[0] if m.get_type() == "GPS_RAW_INT"]
    assert {(m.h_acc, m.v_acc, m.vel_acc) for m in gps} == {(0, 0, 50)}


def test_unknown_accuracies_in_dataflash_and_ulog(tmp_path):
    """Not reported: GPA's HAcc/VAcc/SAcc 0 (as ArduPilot logs it), sensor_gps's eph/epv/s_variance -1
    (as PX4's DroneCAN driver writes it); guard reads both, and the tlog, as unknown."""
    sc = scn.parse({**BASE, "duration_s": 3.0, "noise": {"gnss_h_acc_reported": False,
                                                         "gnss_vel_acc_reported": False}}, "t.toml")
    paths = {k: str(tmp_path / f"run.{k}") for k in ("tlog", "bin", "ulg")}
    run(sc, SEED, **paths)
    conn = mavutil.mavlink_connection(paths["bin"])
    gpa = []
    while (m := conn.recv_match(type="GPA")) is not None:
        gpa.append((m.HAcc, m.VAcc, m.SAcc))
    conn.close()
    assert len(gpa) == 31 and set(gpa) == {(0, 0, 0)}
    gps = ULog(paths["ulg"], ["sensor_gps"]).get_dataset("sensor_gps").data
    for key in ("eph", "epv", "s_variance_m_s"):
        assert set(gps[key].tolist()) == {-1.0}
    for path in paths.values():
        with open_log(path) as reader:
            fixes = [s for s in reader.samples() if hasattr(s, "h_acc_m")]
        assert len(fixes) == 31 and {(f.h_acc_m, f.vel_acc_mps) for f in fixes} == {(None, None)}, path


def test_a_slower_compass_is_held_in_raw_imu_and_written_once_elsewhere(tmp_path):
    """mag_hz 10 beside a 50 Hz IMU: RAW_IMU repeats each reading until the next (as an autopilot's
    does), a new one at every 0.1 s; the DataFlash log's MAG, the ULog's vehicle_magnetometer and
    HIGHRES_IMU's bits carry each reading once; guard reads each as one measurement from all four."""
    sc = scn.parse({**BASE, "duration_s": 6.0, "noise": {"mag_hz": 10.0}}, "t.toml")
    paths = {k: str(tmp_path / f"run.{k}") for k in ("tlog", "bin", "ulg")}
    run(sc, SEED, **paths)
    raw = [m for m in read_tlog(paths["tlog"]) if m.get_type() == "RAW_IMU"]
    mag = [(m.xmag, m.ymag, m.zmag) for m in raw]
    new = [m.time_usec for k, m in enumerate(raw) if k == 0 or mag[k] != mag[k - 1]]
    assert len(raw) == 301 and new == [100_000 * k for k in range(61)]
    conn = mavutil.mavlink_connection(paths["bin"])
    mag_bin = []
    while (m := conn.recv_match(type="MAG")) is not None:
        mag_bin.append(m.TimeUS)
    conn.close()
    assert mag_bin == new
    ulg = ULog(paths["ulg"], ["vehicle_magnetometer"]).get_dataset("vehicle_magnetometer").data
    assert ulg["timestamp"].tolist() == new
    px4 = tmp_path / "px4.tlog"
    url = f"can:virtual:held-{uuid.uuid4().hex[:8]}"
    with CanSource(url, gnss_node_id=None, imu_node_id=None) as source, CanPublisher(url) as publisher:
        run(sc, SEED, tlog=str(px4), autopilot="px4", can=publisher, fast=True)
        while True:         # until a poll waits its whole timeout: the bus's queue is empty
            t0 = time.monotonic()
            if source.poll(0.2) is None and time.monotonic() - t0 >= 0.2:
                break
    assert source.messages["uavcan.equipment.ahrs.MagneticFieldStrength2"] == len(new)
    marked = [m.time_usec for m in read_tlog(px4) if m.get_type() == "HIGHRES_IMU" and m.fields_updated & (0b111 << 6)]
    assert marked == new
    for path in (*paths.values(), str(px4)):
        with open_log(path) as reader:
            read = [s.t_us for s in reader.samples() if getattr(s, "mag_x_gauss", None) is not None]
        if path != paths["tlog"]:
            assert read == new, path
        else:       # RAW_IMU's repeats are told apart once the compass's period is learnt (its first 20 changes)
            learnt = new[20]
            assert set(new) <= set(read) and [t for t in read if t > learnt] == [t for t in new if t > learnt]


@pytest.mark.parametrize("imu_hz", [30.0, 150.0])
def test_a_compass_as_fast_as_the_imu_reads_with_every_sample(tmp_path, imu_hz):
    """A compass at the IMU's rate reads with every sample, even where the period is not a whole number
    of microseconds (the samples' times are rounded to them): the same bytes as without mag_hz."""
    out = {}
    for mag_hz in (0.0, imu_hz):
        sc = scn.parse({**BASE, "duration_s": 3.0, "rates": {"imu_hz": imu_hz, "gnss_hz": 10.0},
                        "noise": {"mag_hz": mag_hz}}, "t.toml")
        out[mag_hz] = tmp_path / f"{mag_hz}.tlog"
        run(sc, SEED, tlog=str(out[mag_hz]))
    assert out[0.0].read_bytes() == out[imu_hz].read_bytes()


# -- rates ----------------------------------------------------------------------------------------------

def test_imu_400_hz_gnss_1_hz_over_30_s(tmp_path):
    sc = scn.parse({**BASE, "rates": {"imu_hz": 400.0, "gnss_hz": 1.0},
                    "attack": [{"kind": "step", "sensor": "gnss_pos", "channel": "north", "magnitude": 10.0,
                                "start_s": 12.5}]}, "t.toml")
    truth = run(sc, SEED, tlog=str(tmp_path / "r.tlog"))
    msgs = read_tlog(tmp_path / "r.tlog")
    imu = [m.time_usec for m in msgs if m.get_type() == "RAW_IMU"]
    gps = [m for m in msgs if m.get_type() == "GPS_RAW_INT"]
    assert imu == [2500 * k for k in range(30 * 400 + 1)]
    assert [m.time_usec for m in gps] == [1_000_000 * k for k in range(31)]
    assert sum(m.get_type() == "HEARTBEAT" for m in msgs) == 31
    assert truth["attacks"][0]["start_gnss_index"] == 13      # the first 1 Hz sample at or after 12.5 s
    st = sc.start
    _, north, _ = pymap3d.geodetic2enu(np.array([m.lat for m in gps]) * 1e-7, np.array([m.lon for m in gps]) * 1e-7,
                                       st.alt_m, st.lat_deg, st.lon_deg, st.alt_m)
    error = np.asarray(north) - np.array(truth["trajectory"]["north_m"])
    assert error[13] - error[12] > 5.0 and abs(error[12] - error[11]) < 3.0


@pytest.mark.parametrize("imu_hz, gnss_hz", [(10.0, 1.0), (25.0, 2.0), (30.0, 3.0), (50.0, 4.0), (70.0, 5.0),
                                             (100.0, 6.0), (150.0, 7.0), (200.0, 8.0), (333.0, 9.0),
                                             (400.0, 10.0)])
def test_rates_and_attack_index(imu_hz, gnss_hz):
    """Every sensor gives duration * rate + 1 samples at round(k * 1e6 / rate) us, and the truth's
    start_gnss_index is the first GNSS sample the attack reaches (also where 1e6 / rate is not whole)."""
    duration_s, start_s = 3.0, 1.0
    sc = scn.parse({**BASE, "duration_s": duration_s, "rates": {"imu_hz": imu_hz, "gnss_hz": gnss_hz},
                    "attack": [{"kind": "step", "sensor": "gnss_pos", "channel": "east", "magnitude": 10.0,
                                "start_s": start_s}]}, "t.toml")
    sim = Simulation(sc, SEED)
    times = {"RAW_IMU": [], "GPS_RAW_INT": []}
    for t_us, messages in sim.ticks():
        for m in messages:
            times.get(m.get_type(), []).append(t_us)
    for name, hz in (("RAW_IMU", imu_hz), ("GPS_RAW_INT", gnss_hz)):
        n = int(round(duration_s * hz)) + 1
        assert times[name] == [int(round(k * 1e6 / hz)) for k in range(n)], name
    first = next(k for k, t in enumerate(times["GPS_RAW_INT"]) if t / 1e6 >= start_s)
    assert sim.truth()["attacks"][0]["start_gnss_index"] == first


# -- validation -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("key, value", [
    ("mag_offset_deg", 30.5), ("mag_offset_deg", -31.0), ("accel_scale", 0.25), ("accel_scale", -0.21),
    ("gyro_scale", 0.3), ("gyro_scale", -1.0), ("imu_yaw_mount_deg", 45.0), ("imu_yaw_mount_deg", -30.01),
    ("mag_wander_deg", -1.0), ("mag_wander_deg", 31.0), ("mag_wander_tau_s", -2.0),
    ("mag_iron_x", 0.51), ("mag_iron_y", -0.7), ("mag_hz", -10.0),
    ("mag_offset_deg", "5"), ("accel_scale", True), ("gnss_vel_acc_reported", 0), ("gnss_h_acc_reported", "no"),
])
def test_bad_value_is_named(key, value):
    with pytest.raises(ScenarioError, match=key):
        scn.parse({**BASE, "noise": {key: value}}, "t.toml")


def test_a_wander_needs_a_correlation_time():
    with pytest.raises(ScenarioError, match="mag_wander_tau_s"):
        scn.parse({**BASE, "noise": {"mag_wander_deg": 2.0, "mag_wander_tau_s": 0.0}}, "t.toml")


@pytest.mark.parametrize("key, value", [("mag_offset_deg", -30), ("accel_scale", 0.2), ("gyro_scale", -0.2),
                                        ("imu_yaw_mount_deg", 30.0), ("gnss_h_acc_reported", False)])
def test_limits_are_inclusive_and_signs_allowed(key, value):
    assert getattr(scn.parse({**BASE, "noise": {key: value}}, "t.toml").noise, key) == value


# -- the wheels' slip -------------------------------------------------------------------------------

def test_a_slipping_vehicle_s_course_turns_outward_of_its_heading_and_its_imu_feels_it():
    """route.sideslip_rad_per_mps2 = k: in a steady left turn the body velocity gains w = -k (omega v) v
    (outward, to the right), the track over ground runs atan(w / v) right of the heading, and the
    lateral specific force is still omega v (w is steady); 0 is the paper's no-slip model."""
    from guard_sim.sensors import Sensors
    from guard_sim.vehicle import Vehicle
    k, v, omega, dt = 0.01, 8.0, 0.3, 0.01
    sc = scn.parse({**BASE, "route": {**BASE["route"], "sideslip_rad_per_mps2": k}}, "slip.toml")
    car = Vehicle(sc.route, 90.0)
    car.s.v = v
    for _ in range(300):                                       # 3 s: the yaw rate is reached and held
        car.step(dt, v, omega)
    assert car.s.omega == pytest.approx(omega) and car.s.w == pytest.approx(-k * omega * v * v)
    e0, n0, psi0 = car.s.e, car.s.n, car.s.psi
    car.step(dt, v, omega)
    course = math.atan2(car.s.n - n0, car.s.e - e0)
    assert math.remainder(course - (psi0 + omega * dt / 2), math.tau) == pytest.approx(
        math.atan2(-k * omega * v * v, v), abs=1e-3)
    quiet = scn.parse({**BASE, "noise": {**NOISELESS, "gnss_vel_white_mps": 0.0}}, "quiet.toml")
    imu = Sensors(quiet, seed=1).imu(0.0, car.s)
    assert -imu.acc_frd[1] == pytest.approx(omega * v, rel=1e-6)           # FRD y is right: left is -y
    gnss = Sensors(quiet, seed=1).gnss(0.0, car.s)
    gnss_course = math.atan2(gnss.vel_n_mps, gnss.vel_e_mps)           # at the step's end, the track's at its middle
    assert math.remainder(gnss_course - car.s.psi, math.tau) == pytest.approx(math.atan2(car.s.w, v), abs=1e-9)
    with pytest.raises(ScenarioError, match="sideslip_rad_per_mps2"):
        scn.parse({**BASE, "route": {**BASE["route"], "sideslip_rad_per_mps2": -0.01}}, "slip.toml")


def test_sensors_ahead_of_the_axle_swing_sideways_in_a_turn_and_feel_its_yaw_acceleration():
    """route.sensors_ahead_m = d: a point d ahead of the axle that does not slide moves sideways at d
    omega in a turn (left in a left turn), and its sideways specific force gains d times the yaw
    acceleration while the yaw rate changes; the GNSS velocity is that point's."""
    from guard_sim.sensors import Sensors
    from guard_sim.vehicle import Vehicle
    d, v, omega, dt = 1.2, 6.0, 0.4, 0.01
    sc = scn.parse({**BASE, "route": {**BASE["route"], "sensors_ahead_m": d}}, "ahead.toml")
    car = Vehicle(sc.route, 90.0)
    car.s.v = v
    car.step(dt, v, omega)                                     # the yaw rate starts to change
    assert car.s.yaw_accel > 0 and car.s.w_dot == pytest.approx(d * car.s.yaw_accel)
    for _ in range(300):                                       # 3 s: the yaw rate is reached and held
        car.step(dt, v, omega)
    assert car.s.omega == pytest.approx(omega) and car.s.w == pytest.approx(d * omega)
    quiet = scn.parse({**BASE, "noise": {**NOISELESS, "gnss_vel_white_mps": 0.0}}, "quiet.toml")
    gnss = Sensors(quiet, seed=1).gnss(0.0, car.s)
    course = math.atan2(gnss.vel_n_mps, gnss.vel_e_mps)
    assert math.remainder(course - car.s.psi, math.tau) == pytest.approx(math.atan2(d * omega, v), abs=1e-9)
    with pytest.raises(ScenarioError, match="sensors_ahead_m"):
        scn.parse({**BASE, "route": {**BASE["route"], "sensors_ahead_m": 4.0}}, "ahead.toml")


def test_a_car_s_steering_moves_its_yaw_acceleration_smoothly():
    """route.max_yaw_jerk_radps3 = J: the yaw acceleration moves at most J dt a step, the yaw rate still
    reaches the command (overshooting it by under 0.5 %), and with a slip the
    sideways specific force, which carries the yaw acceleration times v^2, no longer steps; 0 keeps
    the stepwise model (the yaw rate takes the command at once, within max_yaw_accel_radps2)."""
    from guard_sim.vehicle import Vehicle
    k, v, dt, target = 0.015, 8.0, 0.0025, 0.5
    for jerk in (1.0, 4.0):
        sc = scn.parse({**BASE, "route": {**BASE["route"], "sideslip_rad_per_mps2": k,
                                          "max_yaw_jerk_radps3": jerk}}, "car.toml")
        car = Vehicle(sc.route, 90.0)
        car.s.v = v
        accel, lateral, rates = [], [], []
        for _ in range(int(3.0 / dt)):
            car.step(dt, v, target)
            accel.append(car.s.yaw_accel)
            lateral.append(car.s.w_dot + car.s.omega * car.s.v)
            rates.append(car.s.omega)
        assert max(abs(b - a) for a, b in zip(accel, accel[1:])) <= jerk * dt * (1 + 1e-9)
        assert max(rates) <= 1.005 * target and rates[-1] == pytest.approx(target, abs=1e-3)
        # the sideways force's change in a step: k v^2 times the yaw acceleration's, and v times the yaw rate's
        assert max(abs(b - a) for a, b in zip(lateral, lateral[1:])) < 1.1 * (
            k * v * v * jerk * dt + v * sc.route.max_yaw_accel_radps2 * dt)
    stepwise = Vehicle(scn.parse({**BASE, "route": {**BASE["route"], "sideslip_rad_per_mps2": k}}, "s.toml").route,
                       90.0)
    stepwise.s.v = v
    stepwise.step(dt, v, target)
    a = stepwise.route.max_yaw_accel_radps2
    assert stepwise.s.yaw_accel == pytest.approx(a), "it steps at once"
    assert abs(stepwise.s.w_dot) > 10 * (k * v * v * 4.0 * dt + v * a * dt), "and so does the sideways force"
    with pytest.raises(ScenarioError, match="max_yaw_jerk_radps3"):
        scn.parse({**BASE, "route": {**BASE["route"], "max_yaw_jerk_radps3": -1.0}}, "car.toml")


def test_a_receiver_holds_its_course_below_its_speed_and_measures_it_above(runs):
    """Below gnss_course_hold_mps every fix repeats the last course; above it the course moves with the
    vehicle (and its noise), as without the knob."""
    base, _ = runs()
    held, _ = runs(gnss_course_hold_mps=4.5)
    gps = [(m.vel / 100.0, m.cog) for m in held if m.get_type() == "GPS_RAW_INT"]
    free = [m.cog for m in base if m.get_type() == "GPS_RAW_INT"]
    slow = [i for i in range(1, len(gps)) if gps[i][0] < 4.49]
    fast = [i for i in range(1, len(gps)) if gps[i][0] > 4.51]
    assert len(slow) > 50 and len(fast) > 50
    assert all(gps[i][1] == gps[i - 1][1] for i in slow)
    assert all(gps[i][1] == free[i] for i in fast)
