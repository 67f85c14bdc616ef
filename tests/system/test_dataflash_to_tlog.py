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


@pytest.mark.parametrize("name", ["px4_vtol_cubeorange_short.ulg", "ardupilot_copter_pixhawk1_crash.bin"])
def test_a_real_flight_written_as_px4s_onboard_link_sends_it(shared, tmp_path, name):
    """--px4: the IMU as HIGHRES_IMU at 50 Hz (the latest sample each 20 ms), the magnetometer marked new
    only when a reading came, a PX4 HEARTBEAT; guard reads it back as the same flight at that rate."""
    from pymavlink import mavutil
    src = shared / "data" / "real" / name
    if not src.exists():
        pytest.skip(f"{src} is not here (the shared data folder sits beside the project)")
    out = tmp_path / "px4.tlog"
    got = subprocess.run([sys.executable, str(ROOT / "tools" / "dataflash_to_tlog.py"), "--px4", str(src), str(out)],
                         capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr
    log_report, tlog_report = replay(str(src)), replay(str(out))
    assert "HIGHRES_IMU" in tlog_report["messages"] and "RAW_IMU" not in tlog_report["messages"]
    assert tlog_report["samples"]["gnss"] == log_report["samples"]["gnss"]
    rate, logged = (r["samples"]["imu"] / log_report["duration_s"] for r in (tlog_report, log_report))
    assert 0.9 * min(50.0, logged) <= rate <= min(51.0, logged + 0.1), (rate, logged)     # 50 Hz, or the log's
    conn = mavutil.mavlink_connection(str(out))
    heartbeats, stamps, new_mag = set(), [], 0
    while (m := conn.recv_match(type=["HEARTBEAT", "HIGHRES_IMU"])) is not None:
        if m.get_type() == "HEARTBEAT":
            heartbeats.add(m.autopilot)
        else:
            stamps.append(m.time_usec)
            new_mag += m.fields_updated & 0b111000000 == 0b111000000
    conn.close()
    assert heartbeats == {mavutil.mavlink.MAV_AUTOPILOT_PX4}
    assert min(b - a for a, b in zip(stamps, stamps[1:])) >= 17_500      # never two within 20 ms less half a sample
    assert 0 < new_mag < len(stamps)      # a slower compass: marked new on some samples only
