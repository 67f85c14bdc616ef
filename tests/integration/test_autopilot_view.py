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
