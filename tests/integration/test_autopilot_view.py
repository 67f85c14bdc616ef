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


def test_what_it_cannot_read_is_named(tool, tmp_path, capsys):
    tlog = tmp_path / "flight.tlog"
    tlog.write_bytes(bytes(range(256)) * 4)
    assert tool.main([str(tlog), "--at", "1"]) == 2
    assert str(tlog) in capsys.readouterr().err
    assert tool.main([str(tmp_path / "missing.bin")]) == 2
    assert "missing.bin: cannot open" in capsys.readouterr().err
