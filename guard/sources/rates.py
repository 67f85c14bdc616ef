"""Asking the autopilot for the streams guard reads, at rates it can use.

An autopilot's port sends what it was configured to send: ArduPilot's SRn_ rates (often 0, or the
2 to 4 Hz a ground station asked for), PX4's mode for that port (no IMU at all in its normal mode).
At 1 to 4 Hz guard can test the GNSS only (`monitor.min_imu_hz`). So, as a ground station or a
companion library does, guard asks for what it needs once it hears the autopilot (component 1):
MAV_CMD_SET_MESSAGE_INTERVAL for each message that comes slower than it needs. Not
REQUEST_DATA_STREAM, which older ArduPilot firmware answers instead: it raises a whole group of
messages, and ArduPilot's Plane, Rover, Sub and Tracker save it to their SRn_ parameters, a change
that would outlive guard. What it asks for:

- the IMU at IMU_HZ: RAW_IMU from ArduPilot, HIGHRES_IMU from PX4 (or whichever the vehicle sends);
- GPS_RAW_INT at GNSS_HZ, when its fixes come slower than GNSS_SLOW_HZ (a receiver's own 5 Hz is left
  alone; before the first 3D fix nothing is asked, ArduPilot stamping each message with the last fix);
- ATTITUDE at ATTITUDE_HZ, when slower than ATTITUDE_SLOW_HZ (it levels the IMU).

It never asks for less than comes. It looks again RETRY_S later and asks again, TRIES times in all
for a stream, until it comes at 90 % of the rate asked (a stream that hovers about the threshold is
not asked for again and again); one that has not come faster by then is not asked for again, and an IMU still too slow
to integrate (`monitor.min_imu_hz`) is said once, with the setting that streams it. The streams are
watched for as long as the link lasts, every RECHECK_S: one that slows later (a ground station or a
router that set its own rates on the same port) is asked for again. Everything is asked again when
the autopilot's HEARTBEAT returns after a silence (a reboot forgets what it was asked).
The interval applies to the port the request arrives on (ArduPilot and PX4 alike) and is not saved:
on a port shared with a telemetry radio it would raise the radio's load too; `link.request_rates =
false` asks nothing. Autopilots other than ArduPilot and PX4 are not asked; old ArduPilot firmware
without MAV_CMD_SET_MESSAGE_INTERVAL is not either, and its slow IMU is said.
"""

from __future__ import annotations

from collections import deque

from pymavlink.dialects.v20 import ardupilotmega as mavlink

IMU_HZ, IMU_SLOW_HZ = 50.0, 40.0
GNSS_HZ, GNSS_SLOW_HZ = 10.0, 3.0
ATTITUDE_HZ, ATTITUDE_SLOW_HZ = 25.0, 10.0
WATCH_S = 3.0       # how long the streams are measured before asking
RETRY_S = 5.0       # how long after asking they are measured again
TRIES = 3           # asks for one stream, before it is left as it comes
RECHECK_S = 10.0    # how often the streams are looked at when none is being asked for
SILENCE_S = 5.0     # a HEARTBEAT after this long without one: the autopilot restarted, ask again
DEFAULT_IMU = {mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "RAW_IMU", mavlink.MAV_AUTOPILOT_PX4: "HIGHRES_IMU"}
AUTOPILOT_COMPONENT = mavlink.MAV_COMP_ID_AUTOPILOT1
REACHED = 0.9       # a stream at this share of the rate asked has come: its asks start afresh if it slows
SETTING = {"RAW_IMU": "ArduPilot: SRn_RAW_SENS", "HIGHRES_IMU": "PX4: the port's MAV_n_MODE Onboard"}


class StreamRates:
    """Measures the streams of the autopilot heard and says what to ask for. `heard(msg, now)` for
    every message of the system read; `due(now)` returns the requests to send now, as functions of a
    pymavlink MAVLink object. `say` is how a stream that did not come is said, `tell` how a first ask
    is (what guard changes on the autopilot's port is not done in silence)."""

    def __init__(self, say, enough_hz: float, imu_kind=lambda: None, tell=lambda text: None):
        self.say = say
        self.tell = tell
        self.enough_hz = enough_hz            # an IMU this fast is integrated: slower, it is said
        self.imu_kind = imu_kind              # the IMU message the vehicle sends, once one came
        self.autopilot: tuple[int, int, int] | None = None     # (system, component, MAV_AUTOPILOT_)
        self.arrivals: dict[str, deque] = {}
        self._heartbeat = -1e9
        self._next: float | None = None      # when to look next (None: no autopilot heard yet)
        self._tries: dict[str, int] = {}     # asks so far, per stream still slow

    def heard(self, msg, now: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if msg.autopilot in DEFAULT_IMU and msg.get_srcComponent() == AUTOPILOT_COMPONENT:
                if self.autopilot is None or now - self._heartbeat > SILENCE_S:
                    self.autopilot = (msg.get_srcSystem(), msg.get_srcComponent(), msg.autopilot)
                    self._next = now + WATCH_S
                    self._tries.clear()
                    self.arrivals.clear()
                self._heartbeat = now
            return
        if kind == "GPS_RAW_INT" and msg.fix_type < 3:     # its time is the last fix's: no rate
            return
        stamp = getattr(msg, "time_usec", None)
        stamp = stamp / 1e6 if stamp is not None else getattr(msg, "time_boot_ms", 0) / 1e3
        times = self.arrivals.setdefault(kind, deque())
        times.append((now, stamp))
        while times and now - times[0][0] > WATCH_S:
            times.popleft()

    def rate(self, kind: str, now: float) -> float:
        """Its rate, in Hz of the vehicle's own clock (a sample resent counts once), over what came in
        the last WATCH_S; with one message or none, what came over WATCH_S."""
        stamps = sorted({t for arrived, t in self.arrivals.get(kind, ()) if now - arrived <= WATCH_S})
        if len(stamps) < 2 or stamps[-1] <= stamps[0]:
            return len(stamps) / WATCH_S
        return (len(stamps) - 1) / (stamps[-1] - stamps[0])

    def wanted(self) -> dict[str, tuple[float, float]]:
        """message -> (rate asked for, rate below which it is asked)."""
        imu = self.imu_kind() or DEFAULT_IMU[self.autopilot[2]]
        return {imu: (IMU_HZ, IMU_SLOW_HZ), "GPS_RAW_INT": (GNSS_HZ, GNSS_SLOW_HZ),
                "ATTITUDE": (ATTITUDE_HZ, ATTITUDE_SLOW_HZ)}

    def due(self, now: float) -> list:
        if self._next is None or now < self._next:
            return []
        ask: dict[str, float] = {}
        for kind, (hz, below) in self.wanted().items():
            tries, rate = self._tries.get(kind, 0), self.rate(kind, now)
            if rate >= REACHED * hz:
                self._tries.pop(kind, None)         # it came: asked afresh if it slows
            elif rate >= below or (kind == "GPS_RAW_INT" and kind not in self.arrivals):
                continue                            # fast enough; or no fix yet
            elif tries < TRIES:
                self._tries[kind] = tries + 1
                ask[kind] = hz
            elif tries == TRIES:                    # asked for in vain: left as it comes
                self._tries[kind] = tries + 1
                if kind in SETTING and self.rate(kind, now) < self.enough_hz:
                    self.say(f"{kind} at {self.rate(kind, now):.1f} Hz though asked for {hz:g} Hz: the autopilot "
                             f"did not raise it ({SETTING[kind]})")
        self._next = now + (RETRY_S if ask else RECHECK_S)
        system, component, _ = self.autopilot
        if first := [k for k in ask if self._tries[k] == 1]:
            self.tell(f"asked the autopilot (system {system}) for " + ", ".join(
                f"{k} at {ask[k]:g} Hz (it came at {self.rate(k, now):.1f})" for k in first)
                + "; link.request_rates = false asks nothing")
        return [_interval(system, component, kind, hz) for kind, hz in ask.items()]


def _interval(system: int, component: int, kind: str, hz: float):
    msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{kind}")
    return lambda mav: mav.command_long_send(system, component, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                             msg_id, 1e6 / hz, 0, 0, 0, 0, 0)

