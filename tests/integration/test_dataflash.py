"""ArduPilot DataFlash (.bin): the simulator's writer (sim.dataflash) and guard's reader
(guard.sources.dataflash) as a pair.

One simulated run is written as a tlog and as a .bin at once; both read back give the same samples
(float32 precision) and, replayed, the same alarms. Two real ArduCopter logs (`shared/data/real`
beside the repository) are read as they are. Cut, corrupted, empty and format-only files replay as
far as they can, or fail with a SourceError naming the file, never with a traceback.
"""

import dataclasses
import datetime
import json
import random
import re
import struct
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from toolbox import load_tool

from guard.errors import SourceError
from guard.model.samples import GnssFix, ImuSample, VehicleType
from guard.runtime.replay import replay
from guard.sources import log_format, open_log
from guard_sim import scenario
from guard_sim.dataflash import FMT, HEADER, MSG, LogFormat
from guard_sim.run import run

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT.parent / "shared" / "data" / "real"      # the shared folder beside the repository
CRASH, BURSTY = "ardupilot_copter_pixhawk1_crash.bin", "ardupilot_copter_pixhawk4_bursty.bin"
START_S, DURATION_S = 20.0, 40.0      # tools/eval.py starts attacks at 30 s in 60-105 s runs: shorter here
CASES = ("step east 10 m", "ramp north 0.3 m/s", "spoof north 0.05 m/s2", "freeze", "gyro z bias 0.05 rad/s",
         "accel x bias 0.5 m/s2")
SEEDS = (0, 1)


def eval_cases() -> dict[str, tuple]:
    """The attacks of tools/eval.py's cases named in CASES, started at START_S."""
    harness = load_tool("eval", as_name="guard_eval")
    found = {name: attacks for _, name, attacks, _ in harness.cases(["step", "ramp", "spoof", "freeze", "imu"])}
    return {name: tuple(dataclasses.replace(a, start_s=START_S) for a in found[name]) for name in CASES}


def samples_of(path: str, **options) -> tuple[list, object]:
    with open_log(path, **options) as reader:
        return list(reader.samples()), reader


def alarms(report: dict) -> list[tuple[int, str, str]]:
    return [(a["gnss_index"], str(a["sensor"]), a["channel"]) for a in report["alarms"]]


def message(fmt: LogFormat, *values) -> bytes:
    return HEADER + bytes((fmt.type,)) + fmt.body.pack(*values)


def declare(fmt: LogFormat, length: int | None = None) -> bytes:
    return message(FMT, fmt.type, fmt.length if length is None else length, fmt.name.encode(), fmt.format.encode(),
                   fmt.columns.encode())


@pytest.fixture(scope="module")
def paper(tmp_path_factory) -> tuple[Path, Path]:
    """The paper scenario, 50 s (its attack at GNSS sample 400), as a tlog and a .bin of one run."""
    out = tmp_path_factory.mktemp("paper")
    sc = dataclasses.replace(scenario.load("paper"), duration_s=50.0)
    run(sc, 1, tlog=str(out / "paper.tlog"), bin=str(out / "paper.bin"))
    return out / "paper.tlog", out / "paper.bin"


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> tuple[Path, Path]:
    """30 s of the clean drive (turns, IMU at 50 Hz, a GNSS dropout) as a tlog and a .bin."""
    out = tmp_path_factory.mktemp("drive")
    base = scenario.load("clean")
    dropout = scenario.Attack("dropout", "gnss_pos", "north", 0.0, 12.0, 1.0)
    run(dataclasses.replace(base, duration_s=30.0, attacks=(dropout,)), 3, tlog=str(out / "d.tlog"),
        bin=str(out / "d.bin"))
    return out / "d.tlog", out / "d.bin"


# -- the pair ---------------------------------------------------------------------------------------
def test_the_format_is_found_by_content(paper, tmp_path):
    tlog, bin_ = paper
    assert log_format(str(bin_)) == "dataflash" and log_format(str(tlog)) == "tlog"
    renamed = tmp_path / "flight.log"
    renamed.write_bytes(bin_.read_bytes())
    assert log_format(str(renamed)) == "dataflash"


def test_round_trip_gives_the_tlogs_samples(drive):
    tlog, bin_ = drive
    (from_tlog, tr), (from_bin, br) = samples_of(str(tlog)), samples_of(str(bin_))
    for kind in (GnssFix, ImuSample):
        a, b = [s for s in from_tlog if isinstance(s, kind)], [s for s in from_bin if isinstance(s, kind)]
        assert len(a) == len(b) > 100
        assert [s.t_us for s in a] == [s.t_us for s in b]
    names = [f.name for f in dataclasses.fields(ImuSample)][1:]
    imu_t = np.array([[getattr(s, f) for f in names] for s in from_tlog if isinstance(s, ImuSample)])
    imu_b = np.array([[getattr(s, f) for f in names] for s in from_bin if isinstance(s, ImuSample)])
    assert np.array_equal(imu_t[:, :6].astype(np.float32), imu_b[:, :6])     # float32 in the .bin, exactly
    assert np.array_equal(imu_t[:, 6:], imu_b[:, 6:])                        # milligauss integers both ways
    gt = [s for s in from_tlog if isinstance(s, GnssFix)]
    gb = [s for s in from_bin if isinstance(s, GnssFix)]
    assert [s.fix_ok for s in gt] == [s.fix_ok for s in gb] and not all(s.fix_ok for s in gb)   # the dropout
    assert [(s.lat_deg, s.lon_deg) for s in gt] == [(s.lat_deg, s.lon_deg) for s in gb]       # degE7 both ways
    for f, tol in (("alt_m", 0.006), ("vel_n_mps", 1e-5), ("vel_e_mps", 1e-5), ("h_acc_m", 0.006),
                   ("vel_acc_mps", 0.006)):      # Alt and accuracies in cm, speed and course float32
        assert np.allclose([getattr(s, f) for s in gt], [getattr(s, f) for s in gb], rtol=0, atol=tol), f
    assert [s for s in from_bin if isinstance(s, VehicleType)] == [VehicleType(True)]     # "ArduRover V4.5.0"
    assert br.date == tr.date == datetime.date(2026, 1, 1)
    assert br.notes[0] == "IMU 0: 50.0 Hz, GPS 0: 10.0 Hz, MAG: 50.0 Hz"
    assert br.first_time_us == 0 and br.last_time_us == 30_000_000 and br.position == br.size
    assert br.messages["GPS"] == br.messages["GPA"] == len(gb) and not br.skipped and br.verdicts == []


def _detect(job: tuple) -> tuple:
    """Simulate one case (tlog and .bin of one run) and replay both: (case, seed, tlog alarms, .bin alarms)."""
    name, sc, seed, work = job
    stem = Path(work) / f"{re.sub(r'[^a-z0-9]+', '_', name)}_{seed}"
    run(sc, seed, tlog=f"{stem}.tlog", bin=f"{stem}.bin")
    return name, seed, alarms(replay(f"{stem}.tlog")), alarms(replay(f"{stem}.bin"))


@pytest.fixture(scope="module")
def detections(tmp_path_factory) -> list[tuple]:
    """Every case and seed, on two processes (about 25 s of work)."""
    work = tmp_path_factory.mktemp("detect")
    base = scenario.load("clean")
    runs = [(name, dataclasses.replace(base, name=name, duration_s=DURATION_S, attacks=attacks))
            for name, attacks in eval_cases().items()]
    runs.append(("paper", dataclasses.replace(scenario.load("paper"), duration_s=DURATION_S + 5.0)))
    jobs = [(name, sc, seed, str(work)) for name, sc in runs for seed in SEEDS]
    with ProcessPoolExecutor(max_workers=2) as pool:
        return list(pool.map(_detect, jobs))


def test_detection_is_the_same_from_tlog_and_dataflash(detections):
    for name, seed, from_tlog, from_bin in detections:
        assert len(from_tlog) == len(from_bin), (name, seed, from_tlog, from_bin)
        for (k_t, sensor_t, channel_t), (k_b, sensor_b, channel_b) in zip(from_tlog, from_bin):
            assert (sensor_t, channel_t) == (sensor_b, channel_b) and abs(k_t - k_b) <= 1, (name, seed)
    alarmed = {name for name, _, from_tlog, _ in detections if from_tlog}
    assert len(alarmed) >= 5, alarmed        # not vacuous: the attacks were seen (which, is the detector's business)
    paper_first = [from_bin[0][0] for name, _, _, from_bin in detections if name == "paper"]
    assert paper_first == [400, 400]


# -- real logs ------------------------------------------------------------------------------------------
@pytest.fixture(params=[CRASH, BURSTY])
def real(request) -> Path:
    path = REAL / request.param
    if not path.is_file():
        pytest.skip(f"{path} not found: the real logs live in shared/data/real beside the repository")
    return path


def test_a_real_ardupilot_log_is_read(real):
    got, reader = samples_of(str(real))
    imu = [s for s in got if isinstance(s, ImuSample)]
    gnss = [s for s in got if isinstance(s, GnssFix)]
    assert len(imu) > 1500 and len(gnss) > 300 and sum(s.fix_ok for s in gnss) > 300
    rates = dict(re.findall(r"(IMU 0|GPS 0|MAG|ATT): ([\d.]+) Hz", reader.notes[0]))
    assert 24 <= float(rates["IMU 0"]) <= 26 and 4.5 <= float(rates["GPS 0"]) <= 5.5
    assert 9 <= float(rates["MAG"]) <= 11 and 9 <= float(rates["ATT"]) <= 11
    assert "also IMU 1 at 25.0 Hz, not used: --imu 1 to replay it" in reader.notes
    assert any(n.startswith("autopilot: ") and "Copter" in n for n in reader.notes)
    assert [s for s in got if isinstance(s, VehicleType)] == [VehicleType(False)]
    assert reader.date == {CRASH: datetime.date(2016, 12, 23), BURSTY: datetime.date(2019, 3, 27)}[real.name]
    assert isinstance(reader.verdicts, list)
    assert all(abs(s.acc_z_mps2 + 9.8) < 3 for s in imu[:50])              # specific force, FRD, at rest
    with_mag = [s for s in imu if s.mag_x_gauss is not None]
    # each MAG reading on one IMU sample, the first after it: as many as the readings, not the samples
    assert 0.9 * reader.messages["MAG"] <= len(with_mag) <= reader.messages["MAG"] < 0.5 * len(imu)
    assert all(0.1 < np.hypot(s.mag_x_gauss, s.mag_y_gauss) < 1 for s in with_mag[:50])    # gauss, not mG
    assert reader.first_time_us == min(s.t_us for s in got if not isinstance(s, VehicleType))
    assert reader.messages["IMU"] == len(imu) and reader.position == reader.size


def test_a_real_ardupilot_log_replays(real):
    report = replay(str(real))
    assert report["gnss_samples"] > 300 and report["duration_s"] > 100


def test_a_real_log_with_a_corrupt_type_byte_loses_that_message_only(real, tmp_path):
    """A header a tenth into the log given a type no FMT declares (a corrupt byte on the card): before,
    DFReader's indexer stopped there and the rest of the flight was lost; now that message alone is."""
    data = bytearray(real.read_bytes())
    at = data.index(HEADER, len(data) // 10)
    declared = {data[i + 3] for i in range(len(data) - 4) if data[i:i + 3] == HEADER + bytes((FMT.type,))}
    data[at + 2] = next(t for t in range(1, 128) if t not in declared)
    bad = tmp_path / "corrupt.bin"
    bad.write_bytes(bytes(data))
    whole, report = replay(str(real)), replay(str(bad))
    assert report["skipped"]["undeclared_type"] == 1 and "unread_bytes" not in report["skipped"], report["skipped"]
    assert report["gnss_samples"] >= whole["gnss_samples"] - 1


def fmt_offsets(data: bytes) -> dict[int, int]:
    """The offset of the first FMT declaring each type."""
    out, at = {}, data.find(HEADER + bytes((FMT.type,)))
    while at >= 0:
        out.setdefault(data[at + 3], at)
        at = data.find(HEADER + bytes((FMT.type,)), at + 1)
    return out


def test_a_corrupt_type_byte_naming_a_type_declared_later_is_not_taken_for_its_message(real, tmp_path):
    """ArduPilot writes some FMTs at their first use. A header before such an FMT given its type is not
    one of its messages: dropped and counted; that type's messages after its FMT are all found, and a
    clean log's index is DFReader's own, offset for offset."""
    from guard.sources.dataflash.index import open_index
    from pymavlink import DFReader
    data = real.read_bytes()
    declared = fmt_offsets(data)
    late = max((t for t in declared if t != FMT.type), key=declared.get)
    at = data.index(HEADER, declared[late] // 2)
    corrupt = bytearray(data)
    corrupt[at + 2] = late
    bad = tmp_path / "late.bin"
    bad.write_bytes(bytes(corrupt))
    clean, ours = DFReader.DFReader_binary(str(real)), open_index(str(real))
    assert ours.offsets == clean.offsets and ours.early == 0
    damaged = open_index(str(bad))
    assert damaged.early == 1 and at not in damaged.offsets[late]
    assert damaged.offsets[late] == ours.offsets[late], (len(damaged.offsets[late]), len(ours.offsets[late]))
    whole, report = replay(str(real)), replay(str(bad))
    assert report["skipped"]["undeclared_type"] == 1 and report["gnss_samples"] >= whole["gnss_samples"] - 1


def test_instances_are_chosen_by_number(real):
    first, _ = samples_of(str(real))
    second, reader = samples_of(str(real), imu=1)
    imu = lambda got: [s for s in got if isinstance(s, ImuSample)]        # noqa: E731
    assert len(imu(first)) == len(imu(second)) and imu(first) != imu(second)
    assert reader.notes[0].startswith("IMU 1: 25.0 Hz") and any(n.startswith("also IMU 0") for n in reader.notes)
    with pytest.raises(SourceError, match=re.escape(str(real)) + ".*no IMU 5"):
        open_log(str(real), imu=5)


# -- the autopilot's verdicts ------------------------------------------------------------------------
XKF4 = LogFormat(140, "XKF4", "QBcccccfffHBIHb", "TimeUS,C,SV,SP,SH,SM,SVT,errRP,OFN,OFE,FS,TS,SS,GPS,PI")
ERR = LogFormat(141, "ERR", "QBB", "TimeUS,Subsys,ECode")


def test_verdicts_from_test_ratios_and_messages(tmp_path):
    """EKF3 innovation test ratios above 1 (core 0 only) become episodes; GPS messages are kept."""
    def xkf4(t_s: float, core: int, sv: float, sp: float) -> bytes:
        return message(XKF4, int(t_s * 1e6), core, int(sv * 100), int(sp * 100), 10, 10, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    data = declare(FMT) + declare(XKF4) + declare(ERR) + declare(MSG)
    data += message(MSG, 1_000_000, b"ArduCopter V4.5.0") + message(MSG, 1_000_100, b"GPS 1: detected as u-blox")
    for k in range(200):                # 10 Hz for 20 s: SV above 1 from 5 to 7 s (peak 2.5), again at 9 s
        t = k / 10
        sv = 2.5 if t == 6.0 else 1.5 if 5 <= t <= 7 or t == 9.0 else 0.4
        data += xkf4(t, 0, sv, 0.3) + xkf4(t, 1, 0.2, 3.0 if t > 15 else 0.1)   # core 1: not the primary
    data += message(MSG, 9_050_000, b"GPS Glitch") + message(ERR, 9_060_000, 11, 2) + message(ERR, 11_000_000, 11, 0)
    path = tmp_path / "ekf.bin"
    path.write_bytes(data)
    got, reader = samples_of(str(path))
    assert got == [VehicleType(False)]
    assert reader.verdicts == [
        {"time_usec": 5_000_000, "end_usec": 7_000_000, "source": "EKF3", "test": "gnss_vel", "peak_ratio": 2.5},
        {"time_usec": 9_000_000, "end_usec": 9_000_000, "source": "EKF3", "test": "gnss_vel", "peak_ratio": 1.5},
        {"time_usec": 9_050_000, "source": "autopilot", "test": "message", "text": "GPS Glitch"},
        {"time_usec": 9_060_000, "source": "autopilot", "test": "message", "text": "ERR GPS: glitch"},
        {"time_usec": 11_000_000, "source": "autopilot", "test": "message", "text": "ERR GPS: resolved"}]
    assert "no IMU messages in this log" in reader.notes


UBX3 = LogFormat(142, "UBX3", "IBfff", "TimeMS,Instance,hAcc,vAcc,sAcc")


def test_a_receivers_accuracy_in_ubx3_rows_is_said_not_read(paper, tmp_path):
    """An older log's UBX3 rows carry the receiver's hAcc and sAcc: not read (README, "The receiver's own
    accuracy"), and said, so that the user knows its fixes are tested as an unreporting receiver's."""
    _, bin_ = paper
    unreported = bin_.read_bytes().replace(b"GPA\x00", b"GPZ\x00", 1)    # GPA's rows now an unknown type's
    without, old = tmp_path / "no_gpa.bin", tmp_path / "ubx3.bin"
    without.write_bytes(unreported)
    old.write_bytes(unreported + declare(UBX3)
                    + b"".join(message(UBX3, 1000 + 200 * k, 0, 0.8, 1.2, 0.3) for k in range(100)))
    plain, with_ubx3 = replay(str(without)), replay(str(old))
    said = [n for n in with_ubx3["notes"] if "UBX3" in n]
    assert len(said) == 1 and "is not read" in said[0], with_ubx3["notes"]
    assert not any("UBX3" in n for n in plain["notes"])
    assert alarms(with_ubx3) == alarms(plain) and with_ubx3["peak_ratio"] == plain["peak_ratio"]
    both = tmp_path / "gpa_and_ubx3.bin"      # a log with GPA is read by its GPA: nothing to say
    both.write_bytes(bin_.read_bytes() + declare(UBX3) + message(UBX3, 1000, 0, 0.8, 1.2, 0.3))
    assert not any("UBX3" in n for n in replay(str(both))["notes"])


# -- bad input -----------------------------------------------------------------------------------------
def bad_copies(bin_: Path, out: Path) -> dict[str, Path]:
    """Cut mid-message, overwritten with random bytes in the middle, an undeclared type in the middle,
    the GPS format's length corrupted to 0."""
    data = bin_.read_bytes()
    first_gps = data.index(HEADER + bytes((133,)), 2000)
    copies = {"cut": data[:len(data) // 2 + 7]}
    for seed in range(6):
        rnd, corrupt = random.Random(seed), bytearray(data)
        at, n = rnd.randrange(first_gps, len(data) - 2000), rnd.choice((1, 10, 100, 1000))
        corrupt[at:at + n] = rnd.randbytes(n)
        copies[f"random{seed}"] = bytes(corrupt)
    middle = data.index(HEADER, len(data) // 2)
    copies["undeclared"] = data[:middle] + HEADER + b"\x07" + data[middle + 3:]
    gps_format = data.index(HEADER + bytes((FMT.type, 133)))
    copies["fmt_length_0"] = data[:gps_format + 4] + b"\x00" + data[gps_format + 5:]
    paths = {}
    for name, content in copies.items():
        paths[name] = out / f"{name}.bin"
        paths[name].write_bytes(content)
    return paths


def test_bad_copies_replay_what_they_can_or_say_why(paper, tmp_path):
    _, bin_ = paper
    whole = replay(str(bin_))
    for name, path in bad_copies(bin_, tmp_path).items():
        try:
            report = replay(str(path))
        except SourceError as e:
            assert str(path) in str(e)
            continue
        assert report["gnss_samples"] <= whole["gnss_samples"], name
        if name == "cut":
            assert report["skipped"]["truncated"] == 1 and 0 < report["gnss_samples"] < whole["gnss_samples"]
        if name == "undeclared":            # one corrupt type byte: that message lost, none after it
            assert report["skipped"]["undeclared_type"] == 1 and "unread_bytes" not in report["skipped"]
            assert report["gnss_samples"] >= whole["gnss_samples"] - 1, (report["gnss_samples"], whole["gnss_samples"])
        if name == "fmt_length_0":      # DFReader would loop forever on it: refused, GPS is then undeclared
            assert report["skipped"]["bad_format"] == 1 and report["skipped"]["undeclared_type"] > 0


def test_empty_zero_and_format_only_files(paper, tmp_path):
    empty, zeros, formats = tmp_path / "empty.bin", tmp_path / "zeros.bin", tmp_path / "formats.bin"
    empty.write_bytes(b"")
    zeros.write_bytes(bytes(4096))
    data = paper[1].read_bytes()
    formats.write_bytes(data[:data.index(HEADER + bytes((129,)))])
    for path in (empty, zeros):
        with pytest.raises(SourceError, match=re.escape(str(path))):
            replay(str(path))
    with pytest.raises(SourceError, match="no GNSS sample could be read: found 9 FMT"):
        replay(str(formats))                    # an empty log is an error, never a clean report
    _, reader = samples_of(str(formats))
    assert {"no IMU messages in this log", "no GPS messages in this log"} <= set(reader.notes)


def test_the_cli_never_shows_a_traceback_on_bad_copies(paper, tmp_path):
    paths = bad_copies(paper[1], tmp_path)
    zeros = tmp_path / "zeros.bin"
    zeros.write_bytes(bytes(1000))
    chosen = [paths["cut"], paths["random0"], paths["undeclared"], paths["fmt_length_0"], zeros]
    procs = [(p, subprocess.Popen([sys.executable, "-m", "guard", "replay", str(p), "--report", "-"],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)) for p in chosen]
    for path, proc in procs:
        out, err = proc.communicate(timeout=120)
        assert "Traceback" not in out + err, (path, err)
        if proc.returncode == 0:
            assert json.loads(out)["source"] == str(path)
        else:
            assert str(path) in err and len(err.strip().splitlines()) == 1


# -- a clock that does not keep time -----------------------------------------------------------------
def _restamp(src: Path, dst: Path, boot=lambda t: t, gps_ms=lambda ms: ms) -> None:
    """A copy of a simulator's .bin with its boot time stamps (TimeUS) and GPS times (GMS) remapped."""
    from guard_sim.dataflash import FORMATS, GPS
    by_type = {f.type: f for f in (FMT, *FORMATS)}
    data, p = bytearray(src.read_bytes()), 0
    while p < len(data):
        assert data[p:p + 2] == HEADER
        fmt = by_type[data[p + 2]]
        if fmt.columns.startswith("TimeUS"):
            t, = struct.unpack_from("<Q", data, p + 3)
            struct.pack_into("<Q", data, p + 3, int(boot(t)))
        if fmt is GPS:
            at = p + 3 + struct.calcsize("<QBB")        # TimeUS, I, Status, then GMS
            ms, = struct.unpack_from("<I", data, at)
            struct.pack_into("<I", data, at, int(gps_ms(ms)))
        p += fmt.length
    dst.write_bytes(bytes(data))


def test_an_autopilot_clock_running_slow_is_put_on_the_receivers_time(paper, tmp_path):
    """The paper scenario logged by an autopilot whose clock ran 8 % slow against true time (a 2014
    Linux autopilot's did): every interval it stamped 8 % short, the IMU's with the rest. Read
    against the GNSS receiver's own time, the stamps are scaled back and said; the run is the clean
    log's: the attack at the same GNSS sample, no false alarm."""
    _, bin_ = paper
    skewed = tmp_path / "slow.bin"
    _restamp(bin_, skewed, boot=lambda t: t / 1.08)
    # the autopilot's EKF failed its GNSS velocity gate from 20 to 21 s of true time: stamped by the slow clock
    with skewed.open("ab") as f:
        f.write(declare(XKF4) + b"".join(message(XKF4, round(t / 1.08 * 1e6), 0, 150, 30, 10, 10, 0, 0, 0, 0, 0, 0, 0,
                                                   0, 0) for t in (20.0, 20.5, 21.0)))
    clean, slow = replay(str(bin_)), replay(str(skewed))
    assert not any("clock ran" in n for n in clean["notes"]) and clean["clock"] is None
    said = [n for n in slow["notes"] if "clock ran" in n]
    assert said and "8.0 % slow" in said[0] and "scaled by 1.08" in said[0], slow["notes"]
    assert alarms(slow) == alarms(clean) and alarms(clean)[0][:2] == (400, "gnss_pos")
    # the verdict is moved with the samples: at its true time, where an alarm of that moment would be
    verdict, = slow["autopilot"]
    assert abs(verdict["time_usec"] - 20e6) < 2e4 and abs(verdict["end_usec"] - 21e6) < 2e4, verdict
    assert abs(slow["clock"]["rate"] - 1.08) < 1e-3
    # and back on the log's own clock, where the autopilot's other records are (tools/autopilot_view.py)
    view = load_tool("autopilot_view")
    assert abs(view.report_time_as_logged(verdict["time_usec"], slow["clock"]) - 20e6 / 1.08) < 2e4


def test_a_receiver_time_that_jumps_corrects_nothing(paper, tmp_path):
    """GPS time moved by a minute half-way (a receiver restarting, or a spoofer moving its clock): the
    two clocks are not in a line, so nothing is scaled, and that is said."""
    _, bin_ = paper
    jumped = tmp_path / "jumped.bin"
    mid_ms = None

    def gps_ms(ms):
        nonlocal mid_ms
        mid_ms = ms if mid_ms is None else mid_ms
        return ms + (60_000 if ms - mid_ms > 25_000 else 0)
    _restamp(bin_, jumped, gps_ms=gps_ms)
    report = replay(str(jumped))
    said = [n for n in report["notes"] if "clock ran" in n]
    assert said and "time stamps left as logged" in said[0], report["notes"]
    assert alarms(report) == alarms(replay(str(bin_)))
