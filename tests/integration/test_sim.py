"""The simulator: tlogs read back by plain pymavlink, determinism, attacks, scenario validation, rates.

Attack tests compare a run with one attack against the same scenario and seed without it. Sensor noise
is drawn from seeded streams that do not depend on the vehicle's state, so the two runs see the same
noise; the vehicle, however, steers on the (attacked) GNSS fix, so after the first attacked sample
the true paths part. Hence: before the attack every message is identical; at the first attacked
sample only the attacked channel differs; after it, a GNSS measurement minus the true state (the
truth file's trajectory) differs between the runs by exactly the attack's offset.
"""

import dataclasses
import datetime
import json
import struct
from pathlib import Path

import guard.core.geo
import guard.sources.mavlink  # noqa
import guard.sources.tlog  # noqa
import numpy as np
import pymap3d
import pytest
from pymavlink import mavutil

from guard.runtime.replay import replay
from guard.sinks.plot import Trace
from guard_sim import scenario as scn
from guard_sim.mavout import TLOG_EPOCH_US
from guard_sim.run import Simulation, run
from guard_sim.scenario import Attack, ScenarioError

G = 9.80665


# -- helpers -------------------------------------------------------------------------------------

def read_tlog(path) -> list:
    """Every message of a tlog, in order, with plain pymavlink."""
    conn = mavutil.mavlink_connection(str(path))
    msgs = []
    while (m := conn.recv_match()) is not None:
        msgs.append(m)
    conn.close()
    return msgs


def raw_frames(path) -> list[tuple[int, bytes]]:
    """Split a tlog into (8-byte prefix, MAVLink 2 frame) by hand; fails on anything else."""
    data = Path(path).read_bytes()
    out, pos = [], 0
    while pos < len(data):
        (prefix,) = struct.unpack_from(">Q", data, pos)
        assert data[pos + 8] == 0xFD, f"frame at byte {pos + 8} is not MAVLink 2"
        length = 12 + data[pos + 9] + (13 if data[pos + 10] & 1 else 0)
        out.append((prefix, data[pos + 8:pos + 8 + length]))
        pos += 8 + length
    assert pos == len(data)
    return out


def of_type(msgs, name):
    return [m for m in msgs if m.get_type() == name]


def simulate(tmp_path, sc, seed=3, name="run"):
    path = tmp_path / f"{name}.tlog"
    truth = run(sc, seed, tlog=str(path))
    return read_tlog(path), truth


def gnss_enu(gps_msgs, start):
    """Decoded GPS_RAW_INT -> (east, north, vel_e, vel_n) arrays relative to the scenario start."""
    lat = np.array([m.lat for m in gps_msgs]) * 1e-7
    lon = np.array([m.lon for m in gps_msgs]) * 1e-7
    alt = np.array([m.alt for m in gps_msgs]) / 1000.0
    e, n, _ = pymap3d.geodetic2enu(lat, lon, alt, start.lat_deg, start.lon_deg, start.alt_m)
    speed = np.array([m.vel for m in gps_msgs]) / 100.0
    cog = np.radians(np.array([m.cog for m in gps_msgs]) / 100.0)
    return np.asarray(e), np.asarray(n), speed * np.sin(cog), speed * np.cos(cog)


def truth_enu(truth):
    tr = truth["trajectory"]
    v, psi = np.array(tr["speed_mps"]), np.array(tr["yaw_rad"])
    return np.array(tr["east_m"]), np.array(tr["north_m"]), v * np.cos(psi), v * np.sin(psi)


def fields(m) -> dict:
    return {k: v for k, v in m.to_dict().items() if k != "mavpackettype"}


# -- tlog round trip -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("paper") / "paper.tlog"
    sc = scn.load("paper")
    truth = run(sc, 1, tlog=str(path))
    return sc, path, truth


def test_paper_tlog_reads_back_with_pymavlink(paper_run):
    sc, path, _ = paper_run
    msgs = read_tlog(path)
    n_expected = int(sc.duration_s * 10) + 1
    assert sc.rates.imu_hz == sc.rates.gnss_hz == 10.0
    assert len(of_type(msgs, "GPS_RAW_INT")) == n_expected == 801
    assert len(of_type(msgs, "RAW_IMU")) == n_expected
    assert len(of_type(msgs, "HEARTBEAT")) == int(sc.duration_s * sc.rates.heartbeat_hz) + 1
    assert {m.get_type() for m in msgs} == {"GPS_RAW_INT", "RAW_IMU", "HEARTBEAT"}
    assert all(m.get_msgbuf()[0] == 0xFD for m in msgs), "a frame is not MAVLink 2"
    assert all(m.get_srcSystem() == 1 for m in msgs)
    gps = of_type(msgs, "GPS_RAW_INT")
    assert [m.time_usec for m in gps] == [100_000 * k for k in range(n_expected)]
    assert [m.time_usec for m in of_type(msgs, "RAW_IMU")] == [100_000 * k for k in range(n_expected)]
    assert all(m.fix_type == 3 for m in gps)
    # the paper's drive: north-east at 45 deg, about 5 m/s
    assert 40.0 <= gps[-1].cog / 100.0 <= 50.0
    assert 450 <= gps[-1].vel <= 550


def test_paper_tlog_framing_and_prefix(paper_run):
    _, path, _ = paper_run
    frames = raw_frames(path)
    prefixes = [p for p, _ in frames]
    assert prefixes[0] == TLOG_EPOCH_US
    assert all(b >= a for a, b in zip(prefixes, prefixes[1:])), "tlog time prefix goes backwards"
    assert len(set(prefixes)) == 801          # one time per 10 Hz tick
    # the prefix is the epoch plus the message's own time
    parser = guard.sources.mavlink.mavlink.MAVLink(None)
    for prefix, frame in frames[:50]:
        m = parser.decode(bytearray(frame))
        if hasattr(m, "time_usec"):
            assert prefix - TLOG_EPOCH_US == m.time_usec
    seqs = [f[4] for _, f in frames]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:])), "sequence numbers skip"


def test_truth_json_beside_tlog(paper_run):
    sc, path, returned = paper_run
    truth_path = path.with_name("paper.truth.json")
    assert truth_path.is_file()
    truth = json.loads(truth_path.read_text())
    for key in ("scenario", "seed", "rates", "noise", "attacks"):
        assert key in truth
    assert truth["scenario"] == "paper"
    assert truth["seed"] == 1
    assert truth["rates"] == dataclasses.asdict(sc.rates)
    assert truth["noise"] == dataclasses.asdict(sc.noise)
    assert len(truth["attacks"]) == 1
    a = truth["attacks"][0]
    assert {"kind", "sensor", "channel", "magnitude", "start_time_usec", "start_gnss_index"} <= a.keys()
    assert (a["kind"], a["sensor"], a["channel"], a["magnitude"]) == ("step", "gnss_pos", "north", 10.0)
    assert a["start_time_usec"] == 40_000_000
    assert a["start_gnss_index"] == 400
    assert truth["attacks"] == returned["attacks"]
    assert len(truth["trajectory"]["t_usec"]) == 801


# -- determinism -----------------------------------------------------------------------------------

def test_same_seed_same_bytes_other_seed_other_bytes(paper_run, tmp_path):
    sc, path, _ = paper_run
    run(sc, 1, tlog=str(tmp_path / "again.tlog"))
    run(sc, 2, tlog=str(tmp_path / "other.tlog"))
    first = path.read_bytes()
    assert (tmp_path / "again.tlog").read_bytes() == first
    assert (tmp_path / "other.tlog").read_bytes() != first
    assert len((tmp_path / "other.tlog").read_bytes()) == len(first)     # same frames, other values


def test_the_field_is_that_of_the_scenarios_date_not_the_clocks(tmp_path):
    """The simulator's magnetic field comes from the scenario's year: another year, other bytes."""
    sc = dataclasses.replace(scn.load("paper"), duration_s=2.0)
    run(sc, 1, tlog=str(tmp_path / "a.tlog"))
    run(dataclasses.replace(sc, start=dataclasses.replace(sc.start, year=sc.start.year + 4)), 1,
        tlog=str(tmp_path / "b.tlog"))
    assert (tmp_path / "a.tlog").read_bytes() != (tmp_path / "b.tlog").read_bytes()


def test_a_replay_is_the_same_on_another_day(tmp_path, monkeypatch):
    """The replay takes the magnetic declination on the day the log was recorded, not today."""
    tlog = tmp_path / "clean.tlog"
    run(dataclasses.replace(scn.load("clean"), duration_s=30.0), 1, tlog=str(tlog))
    with guard.sources.tlog.TlogReader(str(tlog)) as reader:
        assert reader.date == datetime.date(2026, 1, 1)     # TLOG_EPOCH_US

    def estimates() -> list:
        trace = Trace()
        replay(str(tlog), listeners=[trace])
        return trace.estimate

    class NoClock(datetime.date):
        @classmethod
        def today(cls):
            raise AssertionError("the core read the clock")

    now = estimates()
    monkeypatch.setattr(datetime, "date", NoClock)       # any date.today() in the replay now fails
    assert estimates() == now


# -- attacks ----------------------------------------------------------------------------------------

START_S = 20.0
K0 = 200            # first GNSS sample at or after START_S at 10 Hz
BASE_SEED = 11


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A turning route, IMU 50 Hz, GNSS 10 Hz, no attack."""
    sc = dataclasses.replace(scn.load("step_east"), name="base", duration_s=32.0, attacks=())
    tmp = tmp_path_factory.mktemp("base")
    msgs, truth = simulate(tmp, sc, BASE_SEED, "base")
    return sc, msgs, truth


def attacked(base, tmp_path, attack):
    """The base scenario with one attack at START_S: the same messages in number, identical before it."""
    sc = dataclasses.replace(base[0], name="attacked", attacks=(attack,))
    msgs, truth = simulate(tmp_path, sc, BASE_SEED, "attacked")
    assert len(msgs) == len(base[1])
    assert truth["attacks"][0]["start_gnss_index"] == K0
    assert truth["attacks"][0]["start_time_usec"] == int(START_S * 1e6)
    assert_identical_before(base[1], msgs, int(START_S * 1e6))
    return msgs, truth


def first_index_at(msgs, t_us):
    """Index in the stream of the first message of the tick at t_us (IMU before GNSS)."""
    for i, m in enumerate(msgs):
        if getattr(m, "time_usec", -1) >= t_us:
            return i
    raise AssertionError(f"no message at {t_us}")


def assert_identical_before(base_msgs, att_msgs, t_us):
    i0 = first_index_at(base_msgs, t_us)
    assert first_index_at(att_msgs, t_us) == i0
    assert i0 > 1000
    for i in range(i0):
        assert base_msgs[i].get_type() == att_msgs[i].get_type()
        assert fields(base_msgs[i]) == fields(att_msgs[i]), f"message {i} differs before the attack"


def imu_at(msgs, t_us):
    (m,) = [m for m in of_type(msgs, "RAW_IMU") if m.time_usec == t_us]
    return m


GNSS_ATTACKS = {
    # id: (attack, first visibly attacked GNSS index, offset(tau) -> (d_east, d_north, d_vel_e, d_vel_n))
    "step_north": (Attack("step", "gnss_pos", "north", 5.0, START_S), K0, lambda tau: (0.0, 5.0, 0.0, 0.0)),
    "step_east": (Attack("step", "gnss_pos", "east", 5.0, START_S), K0, lambda tau: (5.0, 0.0, 0.0, 0.0)),
    "ramp_north": (Attack("ramp", "gnss_pos", "north", 0.3, START_S), K0 + 1,
                   lambda tau: (0.0, 0.3 * tau, 0.0, 0.0)),
    "spoof_north": (Attack("spoof", "gnss_pos", "north", 0.05, START_S), K0 + 1,
                    lambda tau: (0.0, 0.5 * 0.05 * tau * tau, 0.0, 0.05 * tau)),
}


@pytest.mark.parametrize("name", list(GNSS_ATTACKS))
def test_gnss_attack_changes_only_its_channel(base, tmp_path, name):
    attack, k1, offset = GNSS_ATTACKS[name]
    sc, base_msgs, base_truth = base
    att_msgs, att_truth = attacked(base, tmp_path, attack)

    gps_b, gps_a = of_type(base_msgs, "GPS_RAW_INT"), of_type(att_msgs, "GPS_RAW_INT")
    meas_b, meas_a = gnss_enu(gps_b, sc.start), gnss_enu(gps_a, sc.start)

    # first visibly attacked sample: the vehicle has not reacted yet, so compare raw measurements
    t1 = gps_b[k1].time_usec
    tau1 = t1 / 1e6 - START_S
    de, dn, dve, dvn = offset(tau1)
    assert meas_a[0][k1] - meas_b[0][k1] == pytest.approx(de, abs=0.02)
    assert meas_a[1][k1] - meas_b[1][k1] == pytest.approx(dn, abs=0.02)
    if name.startswith("step"):
        assert abs(meas_a[0][k1] - meas_b[0][k1] + meas_a[1][k1] - meas_b[1][k1]) > 4.9     # really moved
        assert (gps_a[k1].vel, gps_a[k1].cog) == (gps_b[k1].vel, gps_b[k1].cog)
    assert gps_a[k1].alt == pytest.approx(gps_b[k1].alt, abs=1)
    assert fields(imu_at(att_msgs, t1)) == fields(imu_at(base_msgs, t1))
    assert att_truth["trajectory"]["north_m"][k1] == base_truth["trajectory"]["north_m"][k1]

    # every attacked sample: measurement minus truth moves by exactly the attack's offset
    true_b, true_a = truth_enu(base_truth), truth_enu(att_truth)
    t = np.array([m.time_usec for m in gps_b]) / 1e6
    after = t >= START_S
    tau = t[after] - START_S
    expected = np.array([offset(x) for x in tau]).T
    tol = (0.03, 0.03, 0.015, 0.015)        # two quantisation steps of lat/lon; 1 cm/s and 0.01 deg
    for axis in range(4):
        got = (meas_a[axis] - true_a[axis]) - (meas_b[axis] - true_b[axis])
        np.testing.assert_allclose(got[after], expected[axis], atol=tol[axis], rtol=0,
                                   err_msg=f"{name}: axis {('east', 'north', 'vel_e', 'vel_n')[axis]}")
    # and the attack is large by the end: it really is in the data
    assert np.abs(expected[:, -1]).max() > 0.5
    # the vehicle follows the attacked fix, so later IMU samples differ: the attack does reach the loop
    assert any(fields(a) != fields(b) for a, b in zip(of_type(att_msgs, "RAW_IMU")[-100:],
                                                       of_type(base_msgs, "RAW_IMU")[-100:]))


def test_freeze_holds_the_fix(base, tmp_path):
    sc, base_msgs, base_truth = base
    att_msgs, _ = attacked(base, tmp_path, Attack("freeze", "gnss_pos", "north", 0.0, START_S))
    gps_b, gps_a = of_type(base_msgs, "GPS_RAW_INT"), of_type(att_msgs, "GPS_RAW_INT")
    frozen = ("lat", "lon", "alt", "vel", "cog")
    held = tuple(getattr(gps_a[K0], f) for f in frozen)
    assert held == tuple(getattr(gps_b[K0], f) for f in frozen)     # the first frozen fix is a true one
    for k in range(K0, len(gps_a)):
        assert tuple(getattr(gps_a[k], f) for f in frozen) == held, f"GNSS sample {k} moved while frozen"
        assert gps_a[k].time_usec == 100_000 * k                     # time stamps still advance
        assert gps_a[k].fix_type == 3
    # the base vehicle kept moving: the frozen values are stale
    assert abs(gps_b[K0 + 20].lat - held[0]) + abs(gps_b[K0 + 20].lon - held[1]) > 50     # > ~5 m in degE7
    t0 = gps_b[K0].time_usec
    assert fields(imu_at(att_msgs, t0)) == fields(imu_at(base_msgs, t0))


IMU_ATTACKS = {
    # id: (attack, RAW_IMU field, expected change in wire units)
    "gyro_z": (Attack("bias", "gyro", "z", 0.05, START_S), "zgyro", 50.0),              # mrad/s
    "accel_x": (Attack("bias", "accel", "x", 0.5, START_S), "xacc", 0.5 / G * 1000.0),  # mG, 50.99
}
IMU_FIELDS = ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "xmag", "ymag", "zmag")


@pytest.mark.parametrize("name", list(IMU_ATTACKS))
def test_imu_bias_changes_only_its_channel(base, tmp_path, name):
    attack, field, expected = IMU_ATTACKS[name]
    sc, base_msgs, _ = base
    att_msgs, _ = attacked(base, tmp_path, attack)

    imu_b, imu_a = of_type(base_msgs, "RAW_IMU"), of_type(att_msgs, "RAW_IMU")
    first = next(i for i, m in enumerate(imu_b) if m.time_usec >= START_S * 1e6)
    assert imu_b[first].time_usec == START_S * 1e6 and first == int(START_S * sc.rates.imu_hz)
    diffs = []
    for i, (a, b) in enumerate(zip(imu_a, imu_b)):
        assert a.time_usec == b.time_usec
        for f in IMU_FIELDS:
            if f != field:
                assert getattr(a, f) == getattr(b, f), f"{name}: {f} changed at IMU sample {i}"
        d = getattr(a, field) - getattr(b, field)
        if i < first:
            assert d == 0, f"{name}: changed before the attack, at IMU sample {i}"
        else:
            diffs.append(d)
    diffs = np.array(diffs)
    assert abs(diffs[0] - expected) <= 1.0      # the first attacked sample, within one wire step
    assert np.all(np.abs(diffs - expected) <= 1.0)
    assert diffs.mean() == pytest.approx(expected, abs=0.2)
    # the vehicle steers on GNSS alone, so an IMU bias leaves every GNSS message untouched
    gps_b, gps_a = of_type(base_msgs, "GPS_RAW_INT"), of_type(att_msgs, "GPS_RAW_INT")
    assert [fields(m) for m in gps_a] == [fields(m) for m in gps_b]


# -- scenario validation ----------------------------------------------------------------------------

MINIMAL = {"name": "t", "duration_s": 10.0}
ATTACK = {"kind": "step", "sensor": "gnss_pos", "channel": "north", "magnitude": 1.0, "start_s": 1.0}


def with_attack(**changes):
    return {**MINIMAL, "attack": [{**ATTACK, **changes}]}


@pytest.mark.parametrize("data, key", [
    ({**MINIMAL, "colour": "red"}, "colour"),
    ({**MINIMAL, "rates": {"imu_hz": 50.0, "baro_hz": 5.0}}, "baro_hz"),
    ({**MINIMAL, "noise": {"gyro_whit_radps": 0.1}}, "gyro_whit_radps"),
    ({**MINIMAL, "start": {"latitude": 40.0}}, "latitude"),
    ({**MINIMAL, "route": {"speed": 3.0}}, "speed"),
    (with_attack(strength=3.0), "strength"),
])
def test_unknown_key_is_named(data, key):
    with pytest.raises(ScenarioError, match=key):
        scn.parse(data, "t.toml")


@pytest.mark.parametrize("data, key", [
    ({**MINIMAL, "duration_s": "long"}, "duration_s"),
    ({"name": 5}, "name"),
    ({**MINIMAL, "rates": {"imu_hz": "fast"}}, "imu_hz"),
    ({**MINIMAL, "start": {"lat_deg": True}}, "lat_deg"),
    ({**MINIMAL, "route": {"loop": 1}}, "loop"),
    ({**MINIMAL, "route": {"waypoints_m": [[0, 0], "north"]}}, "waypoints_m"),
    ({**MINIMAL, "noise": {"gnss_pos_white_m": [0.3]}}, "gnss_pos_white_m"),
    (with_attack(magnitude="big"), "magnitude"),
    (with_attack(start_s="soon"), "start_s"),
    (with_attack(kind=3), "kind"),
])
def test_wrong_type_is_named(data, key):
    with pytest.raises(ScenarioError, match=key):
        scn.parse(data, "t.toml")


@pytest.mark.parametrize("data, key, bad", [
    (with_attack(kind="jam"), "kind", "jam"),
    (with_attack(sensor="baro"), "sensor", "baro"),
    (with_attack(channel="up"), "channel", "up"),
    (with_attack(sensor="gyro", channel="north"), "channel", "north"),
    (with_attack(kind="bias"), "kind", "bias"),                                 # bias on gnss_pos
    (with_attack(kind="bias", sensor="gnss_vel", channel="east"), "kind", "bias"),
    (with_attack(kind="freeze", sensor="accel", channel="x"), "kind", "freeze"),
])
def test_bad_attack_is_named(data, key, bad):
    with pytest.raises(ScenarioError) as e:
        scn.parse(data, "t.toml")
    assert key in str(e.value) and bad in str(e.value)


@pytest.mark.parametrize("imu_hz", [0.0, 9.9, 400.1, 1000.0])
def test_imu_rate_out_of_range(imu_hz):
    with pytest.raises(ScenarioError, match="imu_hz"):
        scn.parse({**MINIMAL, "rates": {"imu_hz": imu_hz}}, "t.toml")


@pytest.mark.parametrize("imu_hz", [10, 400.0])
def test_imu_rate_limits_are_inclusive(imu_hz):
    assert scn.parse({**MINIMAL, "rates": {"imu_hz": imu_hz}}, "t.toml").rates.imu_hz == imu_hz


@pytest.mark.parametrize("mag_hz", [0.001, 0.5, 400.5])
def test_compass_rate_out_of_range(mag_hz):
    with pytest.raises(ScenarioError, match="mag_hz"):
        scn.parse({**MINIMAL, "noise": {"mag_hz": mag_hz}}, "t.toml")


@pytest.mark.parametrize("mag_hz", [0.0, 1, 400.0])
def test_compass_rate_limits_are_inclusive(mag_hz):
    assert scn.parse({**MINIMAL, "noise": {"mag_hz": mag_hz}}, "t.toml").noise.mag_hz == mag_hz


def test_file_error_names_file_and_key(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('name = "mine"\n[rates]\nimu_hz = 50.0\ngps_hz = 5.0\n')
    with pytest.raises(ScenarioError) as e:
        scn.load(str(path))
    assert "mine.toml" in str(e.value) and "gps_hz" in str(e.value)


def test_unknown_scenario_lists_known_names():
    with pytest.raises(ScenarioError) as e:
        scn.load("nosuch")
    message = str(e.value)
    assert "nosuch" in message
    known = scn.names()
    assert {"paper", "clean", "freeze", "spoof"} <= set(known)
    for name in known:
        assert name in message


def test_the_wandering_compass_false_alarms_the_defaults_and_without_its_wander_does_not(tmp_path):
    """The shipped scenario `wandering_compass` is the README's example of a real copter's compass
    (an error of 1.5 degrees correlated over 0.1 s): guard's defaults, which model the compass's error
    as white, alarm on it, first on the magnetometer; the same drive without the wander is quiet."""
    sc = scn.load("wandering_compass")
    runs = {}
    for wander in (sc.noise.mag_wander_deg, 0.0):
        tlog = tmp_path / f"wander-{wander}.tlog"
        run(dataclasses.replace(sc, noise=dataclasses.replace(sc.noise, mag_wander_deg=wander)), 1, tlog=str(tlog))
        runs[wander] = replay(str(tlog))["alarms"]
    assert runs[sc.noise.mag_wander_deg] and runs[sc.noise.mag_wander_deg][0]["sensor"] == "mag"
    assert runs[0.0] == []


def test_every_shipped_scenario_loads():
    for name in scn.names():
        assert scn.load(name).name == name


def test_zero_lookahead_is_rejected_when_loaded():
    try:
        sc = scn.parse({**MINIMAL, "duration_s": 1.0, "route": {"lookahead_m": 0.0}}, "t.toml")
    except ScenarioError as e:
        assert "lookahead_m" in str(e)
        return
    for _ in Simulation(sc, 1).ticks():
        pass


# -- rates ------------------------------------------------------------------------------------------

def test_rates_imu_200_gnss_5(tmp_path):
    base_sc = scn.load("paper")
    sc = dataclasses.replace(base_sc, duration_s=10.0, attacks=(Attack("step", "gnss_pos", "north", 10.0, 3.1),),
                             rates=dataclasses.replace(base_sc.rates, imu_hz=200.0, gnss_hz=5.0))
    msgs, truth = simulate(tmp_path, sc, 5, "rates")
    imu, gps = of_type(msgs, "RAW_IMU"), of_type(msgs, "GPS_RAW_INT")
    assert len(imu) == 10 * 200 + 1
    assert len(gps) == 10 * 5 + 1
    assert len(of_type(msgs, "HEARTBEAT")) == 11
    assert [m.time_usec for m in imu] == [5_000 * k for k in range(2001)]
    assert [m.time_usec for m in gps] == [200_000 * k for k in range(51)]
    assert truth["rates"]["imu_hz"] == 200.0 and truth["rates"]["gnss_hz"] == 5.0
    assert truth["attacks"][0]["start_gnss_index"] == 16       # first 5 Hz sample at or after 3.1 s: 3.2 s
    assert truth["attacks"][0]["start_time_usec"] == 3_100_000
    north = gnss_enu(gps, sc.start)[1] - np.array(truth["trajectory"]["north_m"])
    # the step shows from sample 16 on, not at 15 (noise is ~1 m; 10 m stands out)
    assert north[16] - north[15] > 5.0


def test_valid_but_incommensurate_rates_do_not_spin():
    base_sc = scn.load("paper")
    sc = dataclasses.replace(base_sc, duration_s=1.0, rates=dataclasses.replace(base_sc.rates, imu_hz=300.0))
    scn.parse({**MINIMAL, "rates": {"imu_hz": 300.0}}, "t.toml")      # a valid rate
    for n, (_, messages) in enumerate(Simulation(sc, 1).ticks()):
        assert messages, f"tick {n} carries no message"
        if n > 500:
            break


def test_the_live_link_honours_an_interval_asked_of_it_and_nothing_malformed():
    """SET_MESSAGE_INTERVAL to the simulator's autopilot: a message it sends is honoured and
    acknowledged; NaN or infinite parameters, a message it does not send, another component: denied or
    ignored, never an exception."""
    import math as m
    from pymavlink.dialects.v20 import ardupilotmega as mavlink
    from guard_sim.mavout import COMPONENT_ID, SYSTEM_ID, Encoder, LiveLink
    listener = mavutil.mavlink_connection("udpin:127.0.0.1:0")
    port = listener.port.getsockname()[1]
    honoured: list = []
    link = LiveLink(f"udpout:127.0.0.1:{port}", Encoder(), stream_hz=1.0,
                    on_request=lambda n, i: honoured.append((n, i)))
    asker = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

    def command(p1, p2, component=COMPONENT_ID):
        msg = mavlink.MAVLink(None).decode(bytearray(asker.command_long_encode(
            SYSTEM_ID, component, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, p1, p2, 0, 0, 0, 0, 0).pack(asker)))
        link._command(msg)
    try:
        command(mavlink.MAVLINK_MSG_ID_RAW_IMU, 20_000)
        command(m.nan, 20_000)
        command(mavlink.MAVLINK_MSG_ID_RAW_IMU, m.inf)
        command(mavlink.MAVLINK_MSG_ID_ATTITUDE, 40_000)       # not sent by the simulator
        command(mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 100_000, component=154)
        assert honoured == [("RAW_IMU", 20_000)]
        assert link.interval_us["RAW_IMU"] == 20_000 and link.interval_us["GPS_RAW_INT"] == 1e6
        acks = []
        while (a := listener.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0)) is not None:
            acks.append(a.result)
        assert acks == [mavlink.MAV_RESULT_ACCEPTED] + [mavlink.MAV_RESULT_DENIED] * 3, acks
    finally:
        link.close()
        listener.close()


def test_a_thinned_px4_link_marks_a_compass_reading_new_on_the_next_message_it_sends():
    """A 75 Hz compass among 200 Hz IMU samples, the port sending the IMU at 10 Hz: every HIGHRES_IMU
    that goes out follows a new compass reading, and marks it new (PX4 marks what was updated since the
    last message it published), over real UDP."""
    from guard_sim.mavout import LiveLink
    sc = scn.parse({"name": "t", "duration_s": 3.0, "rates": {"imu_hz": 200.0, "gnss_hz": 5.0},
                         "noise": {"mag_hz": 75.0}}, "t.toml")
    listener = mavutil.mavlink_connection("udpin:127.0.0.1:0")
    port = listener.port.getsockname()[1]
    sim = Simulation(sc, 1, autopilot="px4")
    link = LiveLink(f"udpout:127.0.0.1:{port}", sim.encoder, stream_hz=10.0)
    try:
        held = 0
        for t_us, messages in sim.ticks():
            for msg in messages:
                held += getattr(msg, "mag_held", False)
                link.send(t_us, msg)
        got = []
        while (m := listener.recv_match(type="HIGHRES_IMU", blocking=True, timeout=0.5)) is not None:
            got.append(m.fields_updated & (0b111 << 6) == 0b111 << 6)
    finally:
        link.close()
        listener.close()
    assert held > 100 and len(got) >= 25 and all(got), (held, got)
