"""tools/autopilot_view.py on the real crash flight: at guard's one alarm in flight, the autopilot's
own EKF saw the same GNSS velocity inconsistency (the same axis and direction, its largest of the
flight so far), under vibration past ArduPilot's guidance. The shared data folder sits beside the
project; without it the real-log test skips."""

import json

import pytest
from toolbox import load_tool


@pytest.fixture(scope="module")
def tool():
    return load_tool("autopilot_view")


def test_at_the_crash_flight_s_alarm_the_autopilot_saw_the_same(tool, shared, tmp_path, capsys):
    log = shared / "data" / "real" / "ardupilot_copter_pixhawk1_crash.bin"
    if not log.is_file():
        pytest.skip(f"{log} is not here (the shared data folder sits beside the project)")
    assert tool.main([str(log), "--json", str(tmp_path / "view.json")]) == 0
    views = json.loads((tmp_path / "view.json").read_text())
    first = views[0]
    assert first["alarm"]["sensor"] == "gnss_vel" and first["alarm"]["channel"] == "north"
    # ArduPilot's innovation is its estimate less the measurement: the same inconsistency, opposite sign
    assert first["innovation_north_mps"] * first["alarm"]["offset"] < 0
    assert first["innovation_north_rank"] == 1 and first["innovation_north_windows"] > 10
    assert max(first["vibe_max"]) > tool.ACCEPTABLE_VIBE
    assert "rank 1 of" in capsys.readouterr().out
    # a cut log is read as far as it goes; a time before the alarm is looked at alike
    cut = tmp_path / "cut.bin"
    cut.write_bytes(log.read_bytes()[:300_000])
    assert tool.main([str(cut), "--at", "230", "--window", "2"]) == 0
    assert "vibration" in capsys.readouterr().out


def test_a_px4_log_s_ekf2_innovations_and_vibration(tool, shared, tmp_path, capsys):
    """A PX4 ULog: EKF2's GNSS velocity innovations and the IMU's vibration metrics, read alike. This
    short flight's EKF2 logged its innovations as zeros (it was not fusing the GNSS yet): said so."""
    log = shared / "data" / "real" / "px4_vtol_cubeorange_short.ulg"
    if not log.is_file():
        pytest.skip(f"{log} is not here (the shared data folder sits beside the project)")
    assert tool.main([str(log), "--at", "24", "--at", "26.5", "--json", str(tmp_path / "view.json")]) == 0
    views = json.loads((tmp_path / "view.json").read_text())
    assert [v["ekf"] for v in views] == ["EKF2", "EKF2"]
    assert views[1]["innovation_north_windows"] > views[0]["innovation_north_windows"] >= 1
    assert views[1]["innovation_zero"] and 0 < max(views[1]["vibe_max"]) < 0.01     # m/s: a quiet IMU
    assert not views[1]["vibe_over_limit"] and views[1]["clipping"] == 0
    out = capsys.readouterr().out
    assert "not fusing the GNSS" in out and "PX4's accel m/s" in out
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(log.read_bytes()[:2000])
    assert tool.main([str(cut), "--at", "24"]) in (0, 2)          # read as far as it goes, or named
    err = capsys.readouterr().err
    assert not err or str(cut) in err


def test_what_it_cannot_read_is_named(tool, tmp_path, capsys):
    tlog = tmp_path / "flight.tlog"
    tlog.write_bytes(bytes(range(256)) * 4)
    assert tool.main([str(tlog), "--at", "1"]) == 2
    assert str(tlog) in capsys.readouterr().err
    assert tool.main([str(tmp_path / "missing.bin")]) == 2
    assert "missing.bin: cannot open" in capsys.readouterr().err


def test_a_px4_log_of_before_1_11_is_read_under_its_older_names(tool, tmp_path, capsys):
    """PX4 before 1.11 logged EKF2's innovations as ekf2_innovations (vel_pos_innov: north, east, down
    velocity, then position) and the IMU's vibration in estimator_status (vibe[1] the delta angle's,
    vibe[2] the delta velocity's level). A log written with those topics alone (pyulog's writer): the
    north velocity innovation of its last 2 s read at 4 s, ranked the largest, the vibration read."""
    from guard_sim.ulog import to_ulog
    innov_fields = [("uint64_t", 0, "timestamp"), ("float", 6, "vel_pos_innov")]
    status_fields = [("uint64_t", 0, "timestamp"), ("float", 3, "vibe")]
    innov = [(t * 100_000, 0.5 if t >= 20 else 0.01, -0.02, 0.0, 0.3, 0.1, 0.0) for t in range(41)]
    status = [(t * 100_000, 1e-4, 2e-4, 0.02) for t in range(41)]
    ulog = to_ulog({"ekf2_innovations": innov, "estimator_status": status},
                   {"ekf2_innovations": innov_fields, "estimator_status": status_fields})
    path = tmp_path / "old_px4.ulg"
    ulog.write_ulog(str(path))
    assert tool.main([str(path), "--at", "4", "--window", "2", "--json", str(tmp_path / "view.json")]) == 0
    v, = json.loads((tmp_path / "view.json").read_text())
    assert v["ekf"] == "EKF2" and abs(v["innovation_north_mps"] - 0.5) < 1e-6 and v["innovation_north_rank"] == 1
    assert abs(v["innovation_east_mps"] + 0.02) < 1e-6 and not v["innovation_zero"]
    assert v["vibe_max"] == [0.02, 0.0002] and v["clipping"] == 0
    assert "EKF2 GNSS velocity innovation" in capsys.readouterr().out


def test_an_ardupilot_log_of_before_3_3_is_read_on_its_millisecond_clock(tool, tmp_path, capsys):
    """ArduPilot before 3.3 stamped its records in ms (TimeMS), and its first EKF (EKF1) logged its
    innovations as EKF3 (IVN, IVE ...). Written so, 4 s at 10 Hz whose last 2 s run 0.4 m/s east: read
    on the same seconds as a newer log's, and named EKF1."""
    from guard_sim.dataflash import FMT, HEADER, LogFormat
    ekf3 = LogFormat(140, "EKF3", "Icccccchhhc", "TimeMS,IVN,IVE,IVD,IPN,IPE,IPD,IMX,IMY,IMZ,IVT")

    def message(fmt, *values) -> bytes:
        return HEADER + bytes((fmt.type,)) + fmt.body.pack(*values)
    data = message(FMT, ekf3.type, ekf3.length, b"EKF3", ekf3.format.encode(), ekf3.columns.encode())
    for k in range(41):
        data += message(ekf3, 60_000 + 100 * k, 2, 40 if k >= 20 else 1, 0, 0, 0, 0, 0, 0, 0, 0)
    path = tmp_path / "old_copter.bin"
    path.write_bytes(data)
    assert tool.main([str(path), "--at", "64", "--window", "2", "--json", str(tmp_path / "view.json")]) == 0
    v, = json.loads((tmp_path / "view.json").read_text())
    assert v["ekf"] == "EKF1" and abs(v["innovation_east_mps"] - 0.4) < 1e-6 and v["innovation_east_rank"] == 1
    assert abs(v["innovation_north_mps"] - 0.02) < 1e-6
    assert "EKF1 GNSS velocity innovation" in capsys.readouterr().out
