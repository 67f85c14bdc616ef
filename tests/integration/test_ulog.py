"""PX4 ULog: the simulator's writer (sim.ulog) and guard's reader (guard.sources.ulog) as a pair.

One simulated run is written as a tlog and as a .ulg at once; both read back give the same samples
(float32 precision) and the same alarms. A real PX4 log is read as it is, and cut or corrupted
copies of both replay as far as they can, or fail with a SourceError naming the file, never with
a traceback.
"""

import dataclasses
import json
import random
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pyulog import ULog

from guard.errors import SourceError
from guard.model.samples import GnssFix, ImuSample, VehicleType
from guard.runtime.replay import replay
from guard.sources import log_format, open_log
from guard_sim import scenario
from guard_sim.run import run
from guard_sim.scenario import Attack
from guard_sim.ulog import to_ulog

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "px4_vtol_cubeorange_short.ulg"
START_S = 20.0          # tools/eval.py's cases start at 30 s; 20 s leaves the filter settled and the run short
F32 = dict(rtol=2e-7, atol=1e-7)       # float32's precision on the values a .ulg stores as float
LOSS = {"truncated", "ulog_corrupt", "garbage_bytes", "ulog_bad_time", "imu_out_of_range", "imu_invalid",
        "mag_out_of_range", "gnss_bad_position", "gnss_bad_velocity", "attitude_non_finite"}


def read_all(path, **options):
    with open_log(str(path), **options) as reader:
        return reader, list(reader.samples())


def of(kind, samples):
    return [s for s in samples if isinstance(s, kind)]


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    """The paper's run (60 s, a 2 s GNSS dropout at 20 s) as tlog and .ulg: (tlog, ulg)."""
    d = tmp_path_factory.mktemp("paper")
    sc = scenario.load("paper")
    sc = dataclasses.replace(sc, duration_s=60.0,
                             attacks=sc.attacks + (Attack("dropout", "gnss_pos", "north", 0.0, 20.0, 2.0),))
    run(sc, 1, tlog=str(d / "paper.tlog"), ulg=str(d / "paper.ulg"))
    return d / "paper.tlog", d / "paper.ulg"


# -- round trip ---------------------------------------------------------------------------------

def test_the_format_is_found_by_content(paper):
    assert [log_format(str(p)) for p in paper] == ["tlog", "ulog"]


def test_round_trip_gives_the_tlogs_samples(paper):
    (_, tlog), (reader, ulg) = read_all(paper[0]), read_all(paper[1])
    for kind in (GnssFix, ImuSample):
        a, b = of(kind, tlog), of(kind, ulg)
        assert len(a) == len(b) > 500
        assert [s.t_us for s in a] == [s.t_us for s in b]
    ga, gb = of(GnssFix, tlog), of(GnssFix, ulg)
    assert [g.fix_ok for g in ga] == [g.fix_ok for g in gb] and not all(g.fix_ok for g in ga)
    for name in ("lat_deg", "lon_deg", "alt_m"):
        assert [getattr(g, name) for g in ga] == [getattr(g, name) for g in gb]   # float64 in sensor_gps
    for name in ("vel_n_mps", "vel_e_mps", "h_acc_m", "vel_acc_mps"):
        np.testing.assert_allclose([getattr(g, name) for g in gb], [getattr(g, name) for g in ga], **F32)
    ia, ib = of(ImuSample, tlog), of(ImuSample, ulg)
    for name in ImuSample.__slots__[1:]:
        np.testing.assert_allclose([getattr(s, name) for s in ib], [getattr(s, name) for s in ia], **F32)
    assert of(VehicleType, ulg) == [VehicleType(ground=True)]     # the simulator's rover
    # the order of the stream: at equal time stamps the IMU goes out before the GNSS, as in the tlog
    assert [type(s) for s in tlog if not isinstance(s, VehicleType)] == \
           [type(s) for s in ulg if not isinstance(s, VehicleType)]
    with open_log(str(paper[0])) as tlog_reader:
        assert reader.date == tlog_reader.date          # the same day: the same declination
    assert reader.first_time_us == 0 and reader.last_time_us == 60_000_000
    assert reader.rates_hz == pytest.approx({"sensor_combined": 10.0, "sensor_gps": 10.0,
                                             "vehicle_magnetometer": 10.0})
    assert not reader.skipped and reader.verdicts == []


# -- detection is the same whatever the format ----------------------------------------------------

CASES = {
    "paper": None,
    "step east 10 m": Attack("step", "gnss_pos", "east", 10.0, START_S),
    "ramp north 0.3 m/s": Attack("ramp", "gnss_pos", "north", 0.3, START_S),
    "spoof north": Attack("spoof", "gnss_pos", "north", 0.05, START_S),
    "freeze": Attack("freeze", "gnss_pos", "north", 0.0, START_S),
    "gyro z bias": Attack("bias", "gyro", "z", 0.05, START_S),
    "accel x bias": Attack("bias", "accel", "x", 0.5, START_S),
}
ALARMED = []


@pytest.mark.parametrize("case", CASES)
def test_detection_is_the_same_from_tlog_and_ulog(tmp_path, case):
    attack = CASES[case]
    if attack is None:          # its attack at 40 s
        sc = dataclasses.replace(scenario.load("paper"), duration_s=45.0)
    else:
        sc = dataclasses.replace(scenario.load("clean"), name="ulog", duration_s=40.0, attacks=(attack,))
    for seed in (0, 1):
        run(sc, seed, tlog=str(tmp_path / "a.tlog"), ulg=str(tmp_path / "a.ulg"))
        a, b = replay(str(tmp_path / "a.tlog")), replay(str(tmp_path / "a.ulg"))
        assert a["gnss_samples"] == b["gnss_samples"]
        alarms = [[(x["gnss_index"], str(x["sensor"]), x["channel"]) for x in r["alarms"]] for r in (a, b)]
        assert len(alarms[0]) == len(alarms[1]), (case, seed, alarms)
        for (ka, sa, ca), (kb, sb, cb) in zip(*alarms):
            assert abs(ka - kb) <= 1 and (sa, ca) == (sb, cb), (case, seed, alarms)
        ALARMED.append(bool(alarms[0]))


def test_the_comparison_saw_alarms():
    """Not vacuous: most of the cases above alarmed (which ones is the detector's business)."""
    if not ALARMED:
        pytest.skip("the detection cases did not run")
    assert sum(ALARMED) >= len(ALARMED) // 2


# -- a real PX4 log -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def real():
    if not REAL.is_file():
        pytest.skip(f"the real PX4 log is not here: {REAL}")
    return REAL


def test_a_real_px4_log_is_read(real):
    reader, samples = read_all(real)
    assert len(of(ImuSample, samples)) > 1000 and len(of(GnssFix, samples)) > 25
    with_mag = [s for s in of(ImuSample, samples) if s.mag_x_gauss is not None]
    # each magnetometer reading on one IMU sample, the first after it: as many as the readings
    assert 0.9 * reader.messages["vehicle_magnetometer"] <= len(with_mag) <= reader.messages["vehicle_magnetometer"]
    assert reader.rates_hz["sensor_combined"] == pytest.approx(200, rel=0.05)
    assert reader.rates_hz["vehicle_gps_position"] == pytest.approx(5, rel=0.05)
    assert any("sensor_combined: 200 Hz" in n for n in reader.notes)
    assert any("vehicle_imu" in n for n in reader.notes)      # the three IMUs it did not read
    assert isinstance(reader.verdicts, list)
    assert str(reader.date) == "2021-04-21"
    g = of(GnssFix, samples)[0]
    assert 63 < g.lat_deg < 64 and 10 < g.lon_deg < 11 and 0 < g.h_acc_m < 10
    assert of(ImuSample, samples)[0].acc_z_mps2 == pytest.approx(-9.6, abs=0.3)
    assert of(VehicleType, samples) == [VehicleType(ground=False)]      # a VTOL


def test_a_real_px4_log_replays(real):
    report = replay(str(real))
    assert report["gnss_samples"] > 0 and report["duration_s"] > 5


def test_instances_are_chosen_by_number(real):
    reader, samples = read_all(real, imu=1)
    imu = of(ImuSample, samples)
    assert 5 < len(imu) < 20 and reader.rates_hz["vehicle_imu"] == pytest.approx(2, rel=0.1)
    assert imu[0].acc_z_mps2 == pytest.approx(-9.6, abs=0.3)
    for options in ({"imu": 7}, {"gnss": 3}):
        with pytest.raises(SourceError, match=str(real.name)):
            open_log(str(real), **options)


# -- PX4's own findings ---------------------------------------------------------------------------

def test_verdicts_from_test_ratios_and_messages(tmp_path):
    fields = [("uint64_t", 0, "timestamp"), ("float", 2, "gps_hvel"), ("float", 2, "gps_hpos"),
              ("float", 0, "baro_vpos"), ("float", 0, "heading"), ("float", 3, "mag_field")]
    ratios = [0.2, 1.5, 2.5, 0.3, 0.1, 1.2, 0.4]
    rows = [(t * 100_000, 0.1, 0.0, r, 0.0, 0.1, 0.1, 0.0, 0.0, 0.0) for t, r in enumerate(ratios)]
    ulog = to_ulog({"estimator_innovation_test_ratios": rows}, {"estimator_innovation_test_ratios": fields})
    for t, text in ((150_000, "GPS jamming detected"), (250_000, "Takeoff detected")):
        ulog._logged_messages.append(ULog.MessageLogging(struct.pack("<BQ", ord("4"), t) + text.encode(), None))
    path = tmp_path / "ekf.ulg"
    ulog.write_ulog(str(path))
    reader, _ = read_all(path)
    assert reader.verdicts == [
        {"time_usec": 100_000, "end_usec": 200_000, "source": "EKF2", "test": "gnss_pos", "peak_ratio": 2.5},
        {"time_usec": 150_000, "source": "autopilot", "test": "message", "level": "WARNING",
         "text": "GPS jamming detected"},
        {"time_usec": 500_000, "end_usec": 500_000, "source": "EKF2", "test": "gnss_pos", "peak_ratio": 1.2},
    ]


# -- bad input ----------------------------------------------------------------------------------

def data_start(data: bytes) -> int:
    """The offset of a ULog's first subscription message: where its definitions end."""
    pos = 16
    while data[pos + 2] != ord("A"):
        pos += 3 + struct.unpack_from("<H", data, pos)[0]
    return pos


def overwrite(data: bytes, at: int, n: int, seed: int) -> bytes:
    rng = random.Random(seed)
    return data[:at] + bytes(rng.randrange(256) for _ in range(n)) + data[at + n:]


def bad_copies(path: Path) -> dict[str, bytes]:
    data = path.read_bytes()
    mid = len(data) // 2
    return {
        "empty": b"",
        "magic only": data[:10],
        "header only": data[:16],
        "definitions only": data[:data_start(data)],
        "cut in the definitions": data[:data_start(data) // 2],
        "cut in half": data[:mid],
        "cut 5 bytes short": data[:-5],
        "random bytes in the middle": overwrite(data, mid, 64, 1),
        "random bytes in the definitions": overwrite(data, data_start(data) // 2, 64, 2),
        "random bytes everywhere": scatter(data, 3),
    }


def scatter(data: bytes, seed: int, n: int = 30) -> bytes:
    """`data` with `n` bytes at random places replaced by random ones."""
    rng, out = random.Random(seed), bytearray(data)
    for _ in range(n):
        out[rng.randrange(len(out))] = rng.randrange(256)
    return bytes(out)


def sources(paper):
    out = [("sim", paper[1])]
    if REAL.is_file():
        out.append(("real", REAL))
    return out


def test_bad_copies_replay_what_they_can_or_say_why(paper, tmp_path):
    for origin, good in sources(paper):
        full = len(of(GnssFix, read_all(good)[1]))
        for name, data in bad_copies(good).items():
            path = tmp_path / f"{origin}-{name.replace(' ', '_')}.ulg"
            path.write_bytes(data)
            try:
                report = replay(str(path))
            except SourceError as e:
                assert str(path) in str(e) and "\n" not in str(e), (origin, name, e)
                continue
            lost = LOSS & set(report["skipped"])
            assert report["gnss_samples"] <= full + 1, (origin, name)     # + 1: a corrupt record that passes
            if report["gnss_samples"] < full and name.startswith("cut in half"):
                assert "truncated" in lost, (origin, name, report["skipped"])
            if name.startswith("random bytes in the middle") and report["gnss_samples"] < full:
                assert lost, (origin, name, report["skipped"])


def test_empty_and_cut_headers_are_source_errors(tmp_path):
    for name, data in (("empty", b""), ("magic", b"ULog\x01\x12\x35"), ("garbage", b"ULog\x01\x12\x35" + bytes(9))):
        path = tmp_path / f"{name}.ulg"
        path.write_bytes(data)
        # a whole header and nothing after it reads as an empty log: no GNSS sample, an error too
        with pytest.raises(SourceError, match=path.name):
            replay(str(path))


def guard_command() -> list[str]:
    script = Path(sys.executable).parent / "guard"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "guard"]


def test_the_cli_never_shows_a_traceback_on_bad_copies(paper, tmp_path):
    copies, runs = bad_copies(paper[1]), {}
    for name in ("empty", "cut in half", "random bytes in the middle", "random bytes everywhere"):
        path = tmp_path / f"{name.replace(' ', '_')}.ulg"
        path.write_bytes(copies[name])
        runs[name] = path, subprocess.Popen([*guard_command(), "replay", str(path), "--report", "-"],
                                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for name, (path, proc) in runs.items():
        stdout, stderr = proc.communicate(timeout=120)
        assert "Traceback" not in stdout + stderr, (name, stderr[-2000:])
        if proc.returncode == 0:
            assert json.loads(stdout)["source"] == str(path)    # pyulog's chatter kept off stdout
        else:
            assert str(path) in stderr


def test_a_ulog_stamped_by_a_slow_clock_is_put_on_its_receivers_time(tmp_path):
    """A ULog's fixes carry the receiver's UTC (time_utc_usec): the simulator's clean drive written as
    a ULog whose every boot time stamp is compressed by 8 % (an autopilot clock 8 % slow) is found
    out, said, and replays as the same drive does on a good clock: no alarm."""
    import dataclasses as dc
    import io

    from pyulog import ULog

    from guard.runtime.replay import replay
    from guard_sim import scenario as scn
    from guard_sim.run import run
    from guard_sim.ulog import FORMATS, to_ulog, with_syncs

    sc = dc.replace(scn.load("clean"), duration_s=120.0)
    good = tmp_path / "good.ulg"
    run(sc, 3, ulg=str(good))
    ulog, rows = ULog(str(good)), {}
    for d in ulog.data_list:
        names = [f.field_name for f in d.field_data]
        cols = [d.data[n].copy() for n in names]
        for i, n in enumerate(names):
            if n in ("timestamp", "timestamp_sample"):
                cols[i] = (cols[i] / 1.08).astype(cols[i].dtype)
        rows[d.name] = list(zip(*(c.tolist() for c in cols)))
    buf = io.BytesIO()
    to_ulog(rows, FORMATS).write_ulog(buf)
    slow = tmp_path / "slow.ulg"
    slow.write_bytes(with_syncs(buf.getvalue()))
    assert not [n for n in replay(str(good))["notes"] if "clock" in n]
    report = replay(str(slow))
    said = [n for n in report["notes"] if "clock ran" in n]
    assert len(said) == 1 and "slow against the GNSS receiver's" in said[0] and "scaled by 1.08" in said[0], \
        report["notes"]
    assert report["alarms"] == [], report["alarms"][:3]
