"""tools/real_logs.py: every log in a folder replayed, a line each and the totals; a bad key named
before any log runs."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT


def tool(*args):
    return subprocess.run([sys.executable, str(ROOT / "tools" / "real_logs.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_a_folder_of_logs_is_a_line_each_and_the_totals(shared, tmp_path):
    folder = shared / "data" / "ardupilot-sitl"
    if not folder.is_dir():
        pytest.skip(f"{folder} is not here (the shared data folder sits beside the project)")
    (tmp_path / "notes.txt").write_text("not a log")         # not a log's suffix: not listed
    (tmp_path / "day 2").mkdir()                           # a folder's folders are searched too
    (tmp_path / "day 2" / "broken.tlog").write_bytes(b"\xfe\x00garbage")
    got = tool(folder, tmp_path, "--json", tmp_path / "out.json")
    assert got.returncode == 0, got.stderr
    lines = got.stdout.splitlines()
    assert any(line.startswith("rover_clean_turns.tlog: tlog,") and "alarms 0 (none)" in line for line in lines)
    assert any(line.startswith("broken.tlog: skipped:") for line in lines), lines
    assert lines[-1].startswith("2 logs, ") and "2 logs without one" in lines[-1], lines[-1]
    results = json.loads((tmp_path / "out.json").read_text())
    assert len(results) == 3
    assert all(r["compass_said"] is None and r["compass_said_live"] is None for r in results if "error" not in r)
    # ArduPilot's SITL: its levelled accelerometers agree with its GNSS (README), so guard run would not say they wander
    assert all(r["wander_said_live"] is None for r in results if "error" not in r)
    # nor that its receiver wanders past what guard tune fits (a fault or a spoof: README)
    assert all(r["receiver_beyond_tune"] is False for r in results if "error" not in r)


def test_a_bad_key_or_folder_is_named_and_nothing_runs(tmp_path):
    got = tool(tmp_path, "--set", "monitor.max_wander_factor=0.5")
    assert got.returncode == 2 and "monitor.max_wander_factor" in got.stderr and "Traceback" not in got.stderr
    got = tool(tmp_path / "nowhere")
    assert got.returncode == 2 and "nowhere: no such file or folder" in got.stderr
    (tmp_path / "notes.txt").write_text("not a log")
    got = tool(tmp_path)
    assert got.returncode == 2 and "no log in it or its folders" in got.stderr and "Traceback" not in got.stderr


# long: the campaign tool's attacks on real logs; make test keeps their stream's unit tests
# (tests/unit/test_real_logs_attack.py) and the tool's clean run (above)
@pytest.mark.long
def test_an_attack_written_into_real_fixes_is_caught_and_measured(shared, tmp_path):
    """--attack: each log run again with a 10 m step written into its own fixes at 30, 50 and 70 % of
    them, with a 0.05 rad/s bias written into its yaw gyro and with a 0.5 m/s^2 one into its forward
    accelerometer; on ArduPilot's clean SITL flights every step is caught within a second and every
    bias within 10 s, and the same windows hold no alarm without them. A size that is not a number is refused, named."""
    folder = shared / "data" / "ardupilot-sitl"
    if not folder.is_dir():
        pytest.skip(f"{folder} is not here (the shared data folder sits beside the project)")
    got = tool(folder, "--attack", "step:10", "--attack", "gyro:0.05", "--attack", "accel:0.5",
               "--json", tmp_path / "out.json")
    assert got.returncode == 0, got.stderr
    line, = [x for x in got.stdout.splitlines() if x.strip().startswith("step 10 m:")]
    assert "caught within 5 s in 6 of 6 runs" in line and "without the attack: 0)" in line, line
    for what in ("gyro bias 0.05 rad/s:", "accelerometer bias 0.5 m/s2:"):
        line, = [x for x in got.stdout.splitlines() if x.strip().startswith(what)]
        assert "caught within 10 s in 6 of 6 runs" in line and "without the attack: 0)" in line, line
    import json
    runs = [run for r in json.loads((tmp_path / "out.json").read_text()) for run in r["attacks"]["step:10"]]
    assert len(runs) == 6 and all(run["delay_s"] is not None and run["delay_s"] < 1.0 for run in runs), runs
    assert len({run["onset_us"] for run in runs}) == 6
    bad = tool(folder, "--attack", "step:ten")
    assert bad.returncode == 2 and "step:METRES" in bad.stderr and "Traceback" not in bad.stderr


def test_the_autopilot_is_asked_about_each_gnss_velocity_alarm(shared, tmp_path):
    """--autopilot: each DataFlash or ULog log's own EKF asked about guard's GNSS velocity alarms. The
    crash flight's one alarm came at its EKF's largest velocity inconsistency of the flight so far
    (tests/integration/test_autopilot_view.py); a tlog carries no EKF innovations and is not asked."""
    crash = shared / "data" / "real" / "ardupilot_copter_pixhawk1_crash.bin"
    rover = shared / "data" / "ardupilot-sitl" / "rover_clean_turns.tlog"
    if not (crash.is_file() and rover.is_file()):
        pytest.skip(f"{crash} or {rover} is not here (the shared data folder sits beside the project)")
    got = tool(crash, rover, "--autopilot", "--json", tmp_path / "out.json")
    assert got.returncode == 0, got.stderr
    results = {Path(r["log"]).name: r for r in json.loads((tmp_path / "out.json").read_text())}
    assert results[crash.name]["autopilot_saw"] == [1, 1]
    assert "autopilot_saw" not in results[rover.name]
    assert "the autopilot's own EKF saw 1 of the 1 GNSS velocity alarms" in got.stdout
