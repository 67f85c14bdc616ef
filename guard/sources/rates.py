"""Asking the autopilot for the streams guard reads, at rates it can use.

An autopilot's port sends what it was configured to send: ArduPilot's SRn_ rates (often 0, or the
2 to 4 Hz a ground station asked for), PX4's mode for that port (no IMU at all in its normal mode).
At 1 to 4 Hz guard can test the GNSS only (`monitor.min_imu_hz`). So, as a ground station or a
companion library does, guard asks for what it needs once it hears the autopilot:
MAV_CMD_SET_MESSAGE_INTERVAL for each message that comes slower than it needs (and, from ArduPilot,
REQUEST_DATA_STREAM for its group too, which older firmware answers instead). What it asks for:

- the IMU at IMU_HZ: RAW_IMU from ArduPilot, HIGHRES_IMU from PX4 (or whichever the vehicle sends);
- GPS_RAW_INT at GNSS_HZ, when it comes slower than GNSS_SLOW_HZ (a receiver's own 5 Hz is left alone);
- ATTITUDE at ATTITUDE_HZ, when slower than ATTITUDE_SLOW_HZ (it levels the IMU).

It never asks for less than comes. It looks again RETRY_S later and asks again, TRIES times in all;
an IMU still too slow to integrate (`monitor.min_imu_hz`) is then said once, with the setting that
streams it. The
request is asked again when the autopilot's HEARTBEAT returns after a silence (a reboot forgets it).
The interval applies to the port the request arrives on (ArduPilot and PX4 alike): on a port shared
with a telemetry radio it would raise the radio's load too; `link.request_rates = false` asks
nothing. Autopilots other than ArduPilot and PX4 are not asked.
"""

from __future__ import annotations

from collections import deque

from pymavlink.dialects.v20 import ardupilotmega as mavlink

IMU_HZ, IMU_SLOW_HZ = 50.0, 40.0
GNSS_HZ, GNSS_SLOW_HZ = 10.0, 3.0
ATTITUDE_HZ, ATTITUDE_SLOW_HZ = 25.0, 10.0
WATCH_S = 3.0       # how long the streams are measured before asking
RETRY_S = 5.0       # how long after asking they are measured again
TRIES = 3
SILENCE_S = 5.0     # a HEARTBEAT after this long without one: the autopilot restarted, ask again
DEFAULT_IMU = {mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "RAW_IMU", mavlink.MAV_AUTOPILOT_PX4: "HIGHRES_IMU"}
GROUP = {"RAW_IMU": mavlink.MAV_DATA_STREAM_RAW_SENSORS, "GPS_RAW_INT": mavlink.MAV_DATA_STREAM_EXTENDED_STATUS,
         "ATTITUDE": mavlink.MAV_DATA_STREAM_EXTRA1}       # ArduPilot's groups (its SRn_ parameters)
SETTING = {"RAW_IMU": "ArduPilot: SRn_RAW_SENS", "HIGHRES_IMU": "PX4: the port's MAV_n_MODE Onboard"}


class StreamRates:
    """Measures the streams of the autopilot heard and says what to ask for. `heard(msg, now)` for
    every message of the system read; `due(now)` returns the requests to send now, as functions of a
    pymavlink MAVLink object. `say` is how a stream that did not come is said."""

    def __init__(self, say, imu_kind=lambda: None, enough_hz: float = 8.0):
        self.say = say
        self.enough_hz = enough_hz            # an IMU this fast is integrated: slower, it is said
        self.imu_kind = imu_kind              # the IMU message the vehicle sends, once one came
        self.autopilot: tuple[int, int, int] | None = None     # (system, component, MAV_AUTOPILOT_)
        self.arrivals: dict[str, deque] = {}
        self._heartbeat = -1e9
        self._next = None                     # when to look next (None: nothing more to do)
        self._tries = 0

    def heard(self, msg, now: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if msg.autopilot in DEFAULT_IMU:
                if self.autopilot is None or now - self._heartbeat > SILENCE_S:
                    self.autopilot = (msg.get_srcSystem(), msg.get_srcComponent(), msg.autopilot)
                    self._next, self._tries = now + WATCH_S, 0
                    self.arrivals.clear()
                self._heartbeat = now
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
        slow = {k: hz for k, (hz, below) in self.wanted().items() if self.rate(k, now) < below}
        if not slow or self._tries >= TRIES:
            self._next = None
            for imu in (k for k in slow if k in SETTING and self.rate(k, now) < self.enough_hz):
                self.say(f"{imu} at {self.rate(imu, now):.1f} Hz though asked for {IMU_HZ:g} Hz: the autopilot did "
                         f"not raise it ({SETTING[imu]})")
            return []
        self._tries += 1
        self._next = now + RETRY_S
        system, component, autopilot = self.autopilot
        out = [_interval(system, component, kind, hz) for kind, hz in slow.items()]
        if autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA and self._tries > 1:     # older firmware
            out += [_group(system, component, GROUP[k], hz) for k, hz in slow.items() if k in GROUP]
        return out


def _interval(system: int, component: int, kind: str, hz: float):
    msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{kind}")
    return lambda mav: mav.command_long_send(system, component, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                             msg_id, 1e6 / hz, 0, 0, 0, 0, 0)


def _group(system: int, component: int, group: int, hz: float):
    return lambda mav: mav.request_data_stream_send(system, component, group, int(round(hz)), 1)
