"""Asking the autopilot for its streams (guard.sources.rates): what is asked, when, and of whom.

The messages heard are real pymavlink messages, and what is asked is packed by a real pymavlink
MAVLink object and decoded again; only the clock is the test's, so that seconds pass at once.
"""

import guard.sources.mavlink  # noqa: F401  (sets MAVLINK20=1 before pymavlink is imported)
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from guard.core.monitor import MonitorConfig
from guard.sources import rates

MIN_IMU_HZ = MonitorConfig().min_imu_hz      # the daemon passes the monitor's

AP, PX4 = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, mavlink.MAV_AUTOPILOT_PX4


class Autopilot:
    """Builds the autopilot's messages (system 1, component 1) and decodes what guard asks of it."""

    def __init__(self, autopilot=AP):
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.autopilot = autopilot
        self.guard = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        self.sent: list[bytes] = []
        self.guard.file = self            # guard's packed frames land in self.sent

    def write(self, buf):
        self.sent.append(bytes(buf))

    def _wire(self, msg):
        return mavlink.MAVLink(None).decode(bytearray(msg.pack(self.mav)))

    def heartbeat(self, component=1):
        mav = self.mav if component == 1 else mavlink.MAVLink(None, srcSystem=1, srcComponent=component)
        return mavlink.MAVLink(None).decode(bytearray(
            mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, self.autopilot, 0, 0, 4).pack(mav)))

    def gps(self, t_s, fix_type=3):
        return self._wire(self.mav.gps_raw_int_encode(int(t_s * 1e6), fix_type, 0, 0, 0, 100, 100, 0, 0, 10))

    def raw_imu(self, t_s):
        return self._wire(self.mav.raw_imu_encode(int(t_s * 1e6), 0, 0, -1000, 0, 0, 0, 200, 0, 400))

    def highres_imu(self, t_s):
        return self._wire(self.mav.highres_imu_encode(int(t_s * 1e6), 0, 0, -9.8, 0, 0, 0, 0.2, 0, 0.4,
                                                      1013, 0, 0, 20, 0b111111111))

    def attitude(self, t_s):
        return self._wire(self.mav.attitude_encode(int(t_s * 1e3), 0, 0, 0, 0, 0, 0))

    def asked(self, requests) -> list[tuple]:
        """The requests, sent and decoded: (command or message, message id or group, rate in Hz)."""
        out = []
        for request in requests:
            request(self.guard)
            msg = mavlink.MAVLink(None).decode(bytearray(self.sent.pop()))
            if msg.get_type() == "COMMAND_LONG":
                assert (msg.target_system, msg.target_component) == (1, 1)
                assert msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
                out.append(("interval", mavlink.mavlink_map[int(msg.param1)].msgname, round(1e6 / msg.param2, 3)))
            else:
                raise AssertionError(f"asked with {msg.get_type()}: only SET_MESSAGE_INTERVAL, which is not saved")
        return out


def stream(r: rates.StreamRates, ap: Autopilot, t0: float, t1: float, hz: dict, imu="raw_imu"):
    """Feed the streams at these rates (Hz of the vehicle's clock, which here is the wall's) from t0 to t1,
    a heartbeat each second."""
    events = [(t0 + k, "heartbeat") for k in range(int(t1 - t0) + 1)]
    for kind, f in hz.items():
        events += [(t0 + k / f, kind) for k in range(int((t1 - t0) * f))]
    for t, kind in sorted(events):
        r.heard(getattr(ap, imu if kind == "imu" else kind)(t) if kind != "heartbeat" else ap.heartbeat(), t)


def test_slow_streams_are_asked_for_after_watching_them():
    ap, said, told = Autopilot(), [], []
    r = rates.StreamRates(said.append, MIN_IMU_HZ, tell=told.append)
    stream(r, ap, 0.0, rates.WATCH_S - 0.5, {"gps": 1, "imu": 2, "attitude": 4})
    assert r.due(rates.WATCH_S - 0.5) == [], "asked before watching for WATCH_S"
    stream(r, ap, rates.WATCH_S - 0.5, rates.WATCH_S + 0.1, {"gps": 1, "imu": 2, "attitude": 4})
    assert sorted(ap.asked(r.due(rates.WATCH_S + 0.1))) == [
        ("interval", "ATTITUDE", rates.ATTITUDE_HZ), ("interval", "GPS_RAW_INT", rates.GNSS_HZ),
        ("interval", "RAW_IMU", rates.IMU_HZ)]
    assert said == []
    # what guard changes on the autopilot's port is said, with what came before
    assert len(told) == 1 and "RAW_IMU at 50 Hz (it came at 2.0)" in told[0] and "GPS_RAW_INT at 10 Hz" in told[0]


def test_streams_fast_enough_are_never_asked_for_less():
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    stream(r, ap, 0.0, 4.0, {"gps": 5, "imu": 200, "attitude": 50})      # a 5 Hz receiver is left alone
    assert r.due(4.0) == []
    stream(r, ap, 4.0, 30.0, {"gps": 5, "imu": 200, "attitude": 50})
    assert r.due(30.0) == []


def test_asked_again_then_the_imu_that_did_not_come_is_said_once():
    ap, said = Autopilot(), []
    r = rates.StreamRates(said.append, MIN_IMU_HZ)
    t, tries = 0.0, []
    while t < 60.0:
        stream(r, ap, t, t + 0.5, {"gps": 5, "imu": 2, "attitude": 20})
        t += 0.5
        if asked := r.due(t):
            tries.append(ap.asked(asked))
    assert tries == [[("interval", "RAW_IMU", rates.IMU_HZ)]] * rates.TRIES
    assert (len(said) == 1 and said[0].startswith("RAW_IMU at 2.0 Hz though asked for 50 Hz")
            and "SRn_RAW_SENS" in said[0])


def test_an_imu_raised_but_not_to_50_hz_and_fast_enough_to_integrate_is_not_said():
    ap, said = Autopilot(), []
    r = rates.StreamRates(said.append, MIN_IMU_HZ)
    for t in range(0, 60):
        stream(r, ap, float(t), t + 1.0, {"gps": 5, "imu": 25, "attitude": 20})
        r.due(t + 1.0)
    assert said == []


def test_px4_is_asked_for_highres_imu():
    ap = Autopilot(PX4)
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    stream(r, ap, 0.0, 3.5, {"gps": 5, "attitude": 20})      # PX4's normal mode: no IMU stream at all
    assert ap.asked(r.due(3.5)) == [("interval", "HIGHRES_IMU", rates.IMU_HZ)]
    for t in range(4, 30):
        stream(r, ap, float(t), t + 1.0, {"gps": 5, "attitude": 20})
        ap.asked(r.due(t + 1.0))


def test_the_imu_the_vehicle_sends_is_the_one_asked_for():
    """An ArduPilot that sends HIGHRES_IMU (a vehicle that was set up so) is asked for HIGHRES_IMU."""
    ap = Autopilot(AP)
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ, imu_kind=lambda: "HIGHRES_IMU")
    stream(r, ap, 0.0, 3.5, {"gps": 5, "imu": 4, "attitude": 20}, imu="highres_imu")
    assert ap.asked(r.due(3.5)) == [("interval", "HIGHRES_IMU", rates.IMU_HZ)]


def test_resent_fixes_count_once():
    """ArduPilot resends its last fix at the stream's rate: a 1 Hz receiver streamed at 10 Hz is 1 Hz."""
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    for k in range(40):
        r.heard(ap.gps(k // 10), k / 10)
    assert r.rate("GPS_RAW_INT", 3.9) == pytest.approx(1.0)


def test_rates_are_on_the_vehicles_clock_not_the_links():
    """A burst (a link that held messages back) is not a fast stream."""
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    for k in range(10):
        r.heard(ap.raw_imu(k * 0.5), 2.0 + k * 0.001)      # 10 samples at 2 Hz, arriving within 10 ms
    assert r.rate("RAW_IMU", 2.1) == pytest.approx(2.0)


def test_asked_again_after_the_autopilot_restarts():
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    t = 0.0
    while t < 40.0:
        stream(r, ap, t, t + 0.5, {"gps": 1, "imu": 50, "attitude": 20})
        t += 0.5
        r.due(t)
    assert r.due(t) == []                                   # done: the GNSS did not come faster
    stream(r, ap, t + 10.0, t + 10.0 + rates.WATCH_S + 0.5, {"gps": 1, "imu": 50, "attitude": 20})
    assert ap.asked(r.due(t + 10.0 + rates.WATCH_S + 0.5)) == [("interval", "GPS_RAW_INT", rates.GNSS_HZ)]


def test_an_autopilot_of_another_kind_is_not_asked():
    ap = Autopilot(mavlink.MAV_AUTOPILOT_GENERIC)
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    stream(r, ap, 0.0, 10.0, {"gps": 1, "imu": 1})
    assert r.due(10.0) == []


def test_a_stream_slowed_later_is_asked_for_again():
    """A ground station on the same port sets RAW_IMU to 4 Hz a minute in: guard asks for 50 again."""
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    asked, t = [], 0.0
    while t < 100.0:
        stream(r, ap, t, t + 0.5, {"gps": 5, "imu": 50 if t < 60.0 else 4, "attitude": 20})
        t += 0.5
        asked += [(t, a) for a in ap.asked(r.due(t))]
    assert asked, "the slowed IMU was not asked for"
    assert all(a == ("interval", "RAW_IMU", rates.IMU_HZ) for _, a in asked), asked
    first = asked[0][0]
    assert 60.0 < first <= 60.0 + rates.WATCH_S + rates.RECHECK_S + 0.5, first


def test_a_stream_that_never_comes_does_not_stop_the_others_being_watched():
    """ATTITUDE never comes (asked TRIES times, then left); the IMU, slowed later, is still asked for."""
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    asked, t = [], 0.0
    while t < 120.0:
        stream(r, ap, t, t + 0.5, {"gps": 5, "imu": 50 if t < 80.0 else 2})
        t += 0.5
        asked += [a for a in ap.asked(r.due(t)) if a[0] == "interval"]
    assert [a[1] for a in asked].count("ATTITUDE") == rates.TRIES
    assert ("interval", "RAW_IMU", rates.IMU_HZ) in asked


def test_no_fix_yet_is_no_slow_receiver():
    """ArduPilot stamps GPS_RAW_INT with its last fix: before the first, every message has one time.
    Nothing is asked of the GNSS until fixes come, and then only if they come slowly."""
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    t = 0.0
    while t < 30.0:
        for k in range(5):
            r.heard(ap.gps(0.0, fix_type=1), t + k / 5)
        stream(r, ap, t, t + 1.0, {"imu": 50, "attitude": 20})
        t += 1.0
        assert r.due(t) == []
    stream(r, ap, t, t + 4.0, {"gps": 1, "imu": 50, "attitude": 20})
    assert ap.asked(r.due(t + 4.0)) == [("interval", "GPS_RAW_INT", rates.GNSS_HZ)]


def test_only_the_autopilot_component_is_asked():
    """A HEARTBEAT of another component of the vehicle (a camera, a gimbal with the autopilot field
    set) names no one to ask."""
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    for k in range(10):
        r.heard(ap.heartbeat(component=154), float(k))
        r.heard(ap.raw_imu(float(k)), float(k))
    assert r.due(10.0) == [] and r.autopilot is None


def test_a_stream_about_the_threshold_is_not_asked_for_again_and_again():
    """An IMU wandering between 37 and 44 Hz: asked for once it falls under 40, then left until it
    has come at 90 % of the 50 Hz asked; not an ask every time it dips."""
    ap = Autopilot()
    r = rates.StreamRates(lambda text: None, MIN_IMU_HZ)
    asked, t = 0, 0.0
    while t < 600.0:
        hz = 37.0 if int(t / 7) % 2 else 44.0
        stream(r, ap, t, t + 1.0, {"gps": 5, "imu": hz, "attitude": 20})
        t += 1.0
        asked += len(ap.asked(r.due(t)))
    assert asked == rates.TRIES, asked
