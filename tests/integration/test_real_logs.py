"""guard on logs the simulator did not make: real flights (DataFlash, ULog) and ArduPilot's SITL, and
the SITL logs as telemetry streams them (1 Hz, a reboot in the middle, repeated frames). None holds an
attack. The files sit beside the project in the shared data folder; without it these tests skip."""

import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil                                   # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink     # noqa: E402

from guard.core.geo import LocalFrame                           # noqa: E402
from guard.runtime.replay import replay                         # noqa: E402
from guard.sinks.plot import Trace                              # noqa: E402


def need(path):
    if not path.exists():
        pytest.skip(f"{path} is not here (the shared data folder sits beside the project)")
    return str(path)


def worst_distance_to_fixes(trace: Trace) -> float:
    """The largest distance between an estimate and the fix of the same time."""
    frame = LocalFrame(*trace.origin)
    fixes = {t: frame.to_en(lat, lon) for t, lat, lon in trace.gnss}
    return max(float(np.hypot(e - fixes[t][0], n - fixes[t][1])) for t, e, n in trace.estimate if t in fixes)


@pytest.mark.parametrize("name", ["ardupilot_copter_pixhawk4_bursty.bin", "px4_vtol_cubeorange_short.ulg"])
def test_a_real_clean_flight_raises_no_alarm_and_the_estimate_stays_on_the_fixes(shared, name):
    trace = Trace()
    report = replay(need(shared / "data" / "real" / name), listeners=[trace])
    assert report["alarms"] == [], report["alarms"][:3]
    assert report["gnss_samples"] > 20 and report["notes"]
    assert worst_distance_to_fixes(trace) < 5.0
    assert 0.0 < report["estimate_to_fix_m"]["max"] < 5.0       # the report's own measure, against the fix fused
    assert abs(report["compass_offset_still_rad"]) < 0.5          # what guard tune would write of its compass


def test_the_crash_log_says_its_blow_and_little_before(shared):
    """A real flight that ends in a mechanical failure: whatever guard says, it says little before the
    failure, and the estimate follows the fixes until then. The crash itself (the IMU reads 16 g) is a
    blow the IMU cannot measure (guard.core.aiding.impact): said, set aside, not an alarm."""
    trace = Trace()
    report = replay(need(shared / "data" / "real" / "ardupilot_copter_pixhawk1_crash.bin"), listeners=[trace])
    end = report["gnss_samples"]
    before = [a for a in report["alarms"] if a["gnss_index"] < end - 50]       # the last 10 s: the crash
    assert len(before) <= 1, before
    last = trace.gnss[-1][0]
    blows = [n for n in report["notices"] if "blow at the IMU" in n["text"]]
    assert len(blows) == 1 and last - blows[0]["time_usec"] < 10e6, blows
    assert [a for a in report["alarms"] if a["gnss_index"] >= end - 50] == []     # the crash: no alarm
    assert report["skipped"]["imu_impact"] > 0


def thin(src: str, dst: str, hz: float) -> None:
    """A telemetry-like copy of a tlog: GPS_RAW_INT and RAW_IMU at `hz` at most, the autopilot's boot
    clock starting again at 30 s half-way through (a reboot), every 97th frame sent twice."""
    conn = mavutil.mavlink_connection(src)
    msgs = []
    while (m := conn.recv_match()) is not None:
        if m.get_type() != "BAD_DATA":
            msgs.append(m)
    t_mid, shift, last, mav = msgs[len(msgs) // 2]._timestamp, None, {}, mavlink.MAVLink(None)
    with open(dst, "wb") as out:
        for n, m in enumerate(msgs):
            buf = m.get_msgbuf()
            if m.get_type() in ("GPS_RAW_INT", "RAW_IMU"):
                t = m.time_usec
                if t and m.get_type() in last and t - last[m.get_type()] < 1e6 / hz - 5000:
                    continue
                last[m.get_type()] = t
                if m._timestamp >= t_mid and t:
                    shift = shift if shift is not None else t - 30_000_000
                    m.time_usec = t - shift
                mav.seq, mav.srcSystem, mav.srcComponent = m.get_seq(), m.get_srcSystem(), m.get_srcComponent()
                buf = m.pack(mav)
            frame = int(m._timestamp * 1e6).to_bytes(8, "big") + bytes(buf)
            out.write(frame * (2 if n % 97 == 0 else 1))


@pytest.mark.parametrize("name", ["rover_clean_turns", "copter_clean_straight"])
@pytest.mark.parametrize("hz", [1.0, 1000.0])
def test_autopilot_logs_as_telemetry_streams_them(shared, tmp_path, name, hz):
    """At 1 Hz the IMU is not integrated (said once) and GNSS is tested on its own; at full rate the
    reboot re-initialises the filter once; repeated frames are counted; no alarm either way; and the
    accelerometers' reading at rest is judged at either rate, and found to be g."""
    path = str(tmp_path / f"{name}.tlog")
    thin(need(shared / "data" / "ardupilot-sitl" / f"{name}.tlog"), path, hz)
    report = replay(path)
    notes = [n["text"] for n in report["notices"]]
    assert report["alarms"] == [], report["alarms"][:3]
    assert sum("filter re-initialised" in n for n in notes) == 1, notes
    assert sum("not integrated" in n for n in notes) == (1 if hz < 8 else 0), notes
    assert report["skipped"].get("gnss_resent", 0) + report["skipped"].get("imu_resent", 0) > 0
    rest = report["accelerometers_at_rest"]             # judged at rest at either rate; SITL's IMU reads g
    assert rest["windows"] >= 2 and abs(rest["median_mps2"] - 9.80665) < 0.1, rest
    assert not [n for n in notes if "at rest over" in n]


def test_the_autopilots_attitude_is_carried_to_each_imu_sample_by_the_gyro(shared):
    """The attitude that levels the IMU comes at 10 Hz, apart from the IMU's 25 Hz: carried forward
    with the gyro it predicts the autopilot's next attitude (the 99th percentile of the error in
    roll and pitch) several times better than holding the last one, on a real copter's flight."""
    from guard.core.aiding.tilt import Tilt
    from guard.model.samples import Attitude, ImuSample
    from guard.sources import open_log
    source = open_log(need(shared / "data" / "real" / "ardupilot_copter_pixhawk1_crash.bin"), system_id=0)
    tilt, held, carried, kept = Tilt(), [], [], None
    try:
        for s in source.samples():
            if isinstance(s, Attitude):
                if kept is not None and tilt.t_us != tilt.t_att:       # carried by at least one IMU sample
                    carried.append(np.hypot(s.roll_rad - tilt.roll, s.pitch_rad - tilt.pitch))
                    held.append(np.hypot(s.roll_rad - kept[0], s.pitch_rad - kept[1]))
                tilt.set(s)
                kept = (s.roll_rad, s.pitch_rad)
            elif isinstance(s, ImuSample):
                tilt.at(s)
    finally:
        source.close()
    assert len(carried) > 1000
    assert np.percentile(carried, 99) < 0.3 * np.percentile(held, 99), (np.percentile(carried, 99),
                                                                         np.percentile(held, 99))


def slow_clock(src: str, dst: str, rate: float) -> None:
    """A copy of a tlog stamped by an autopilot clock that runs `rate` times too slow: every boot
    time (GPS_RAW_INT, RAW_IMU, ATTITUDE) compressed about the first, the ground station's prefix kept."""
    conn = mavutil.mavlink_connection(src)
    mav, t0 = mavlink.MAVLink(None), None
    with open(dst, "wb") as out:
        while (m := conn.recv_match()) is not None:
            if m.get_type() == "BAD_DATA":
                continue
            buf = m.get_msgbuf()
            field, scale = {"GPS_RAW_INT": ("time_usec", 1), "RAW_IMU": ("time_usec", 1),
                            "ATTITUDE": ("time_boot_ms", 1000)}.get(m.get_type(), (None, 1))
            if field:
                t = getattr(m, field) * scale
                t0 = t if t0 is None else t0
                setattr(m, field, round((t0 + (t - t0) / rate) / scale))
                mav.seq, mav.srcSystem, mav.srcComponent = m.get_seq(), m.get_srcSystem(), m.get_srcComponent()
                buf = m.pack(mav)
            out.write(int(m._timestamp * 1e6).to_bytes(8, "big") + bytes(buf))


def test_a_tlog_stamped_by_a_slow_clock_is_put_on_its_receivers_time(shared, tmp_path):
    """A tlog carries no GNSS time: its clock is checked against the receiver's own motion. ArduPilot's
    SITL copter flown straight, as logged: nothing said; its time stamps compressed by 8 % (the Erle
    autopilot's clock): the 8 % found, within a few tenths, said, undone, and still no alarm."""
    src = need(shared / "data" / "ardupilot-sitl" / "copter_clean_straight.tlog")
    report = replay(src)
    assert not [n for n in report["notes"] if "clock" in n], report["notes"]
    slow = str(tmp_path / "slow.tlog")
    slow_clock(src, slow, 1.08)
    report = replay(slow)
    said = [n for n in report["notes"] if "clock ran" in n]
    assert len(said) == 1 and " slow against its receiver's own motion" in said[0], report["notes"]
    assert abs(float(said[0].rsplit(" ", 1)[1]) - 1.08) < 0.005, said
    assert report["alarms"] == [], report["alarms"][:3]


def test_fixes_stamped_in_unix_time_beside_an_imu_from_boot_are_joined(shared, tmp_path):
    """MAVLink lets GPS_RAW_INT carry UNIX time while RAW_IMU counts from boot. ArduPilot's SITL
    rover with its fixes so stamped: said once, the fixes put on the boot clock by their arrival,
    nothing dropped as off the time base, and the flight replays as it does stamped from boot."""
    src = need(shared / "data" / "ardupilot-sitl" / "rover_clean_turns.tlog")
    shift = 1_700_000_000_000_000
    conn, mav, dst = mavutil.mavlink_connection(src), mavlink.MAVLink(None), str(tmp_path / "unix.tlog")
    with open(dst, "wb") as out:
        while (m := conn.recv_match()) is not None:
            if m.get_type() == "BAD_DATA":
                continue
            buf = m.get_msgbuf()
            if m.get_type() == "GPS_RAW_INT" and m.time_usec:
                m.time_usec += shift
                mav.seq, mav.srcSystem, mav.srcComponent = m.get_seq(), m.get_srcSystem(), m.get_srcComponent()
                buf = m.pack(mav)
            out.write(int(m._timestamp * 1e6).to_bytes(8, "big") + bytes(buf))
    base, joined = replay(src), replay(dst)
    said = [n for n in joined["notes"] if "UNIX time" in n]
    assert len(said) == 1, joined["notes"]
    assert "time_off_base" not in joined["skipped"], joined["skipped"]
    assert joined["gnss_samples"] == base["gnss_samples"] and joined["alarms"] == base["alarms"] == []
    assert joined["estimate_to_fix_m"]["max"] < 1.0, joined["estimate_to_fix_m"]
