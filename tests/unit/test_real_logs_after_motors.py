"""tools/real_logs.py's count of the alarms the take-off brings: each new alarm's time after the
latest motors' start guard heard before it, from the report's own notices."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))    # tools, beside guard
from tools.real_logs import after_motors  # noqa: E402


def notice(t_s, text):
    return {"time_usec": int(t_s * 1e6), "level": "info", "text": text}


def alarm(t_s, standing=False):
    return {"time_usec": int(t_s * 1e6), "sensor": "mag", "standing": standing}


def test_each_new_alarm_is_timed_from_the_latest_start_before_it_and_a_window_s_close_is_no_start():
    report = {"notices": [notice(100.0, "the motors started (the IMU's vibration): ..."),
                          notice(120.0, "the compass turned +12.0 deg in the 20 s after the motors started (...)"),
                          notice(200.0, "the motors stopped (the IMU's vibration): ..."),
                          notice(300.0, "the motors started (the IMU's vibration): ...")],
              "alarms": [alarm(50.0), alarm(104.5), alarm(125.0), alarm(126.0, standing=True), alarm(301.0)]}
    assert after_motors(report) == [None, 4.5, 25.0, 1.0]
