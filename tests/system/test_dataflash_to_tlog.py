"""tools/dataflash_to_tlog.py: a real DataFlash flight written as the tlog a ground station would have
recorded replays as the same flight (every fix and IMU sample, the same vehicle, the same clock)."""

import subprocess
import sys

import pytest

from conftest import ROOT
from guard.runtime.replay import replay


def test_a_real_flight_written_as_a_tlog_replays_as_the_same_flight(shared, tmp_path):
    src = shared / "data" / "real" / "ardupilot_copter_pixhawk1_crash.bin"
    if not src.exists():
        pytest.skip(f"{src} is not here (the shared data folder sits beside the project)")
    out = tmp_path / "crash.tlog"
    got = subprocess.run([sys.executable, str(ROOT / "tools" / "dataflash_to_tlog.py"), str(src), str(out)],
                         capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr
    bin_report, tlog_report = replay(str(src)), replay(str(out))
    assert tlog_report["format"] == "tlog"
    assert tlog_report["samples"] == bin_report["samples"], (tlog_report["samples"], bin_report["samples"])
    assert tlog_report["messages"]["GPS_RAW_INT"] == bin_report["samples"]["gnss"]
    assert abs(tlog_report["duration_s"] - bin_report["duration_s"]) < 1.0
    assert not [n for n in tlog_report["notes"] if "clock" in n]        # a Pixhawk keeps time
    assert tlog_report["alarms"] and len(tlog_report["alarms"]) <= len(bin_report["alarms"]) + 3
    missing = subprocess.run([sys.executable, str(ROOT / "tools" / "dataflash_to_tlog.py"), str(tmp_path / "no.bin"),
                              str(out)], capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "no.bin: no such file or folder" in missing.stderr
