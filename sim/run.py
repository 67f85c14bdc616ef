"""The simulator's main loop: vehicle, sensors and attacks on one integer-microsecond clock.

Sample k of every sensor is taken at k / rate seconds from t = 0 (rounded to the microsecond), so
with GNSS at 10 Hz an attack starting at 40 s hits GNSS sample 400 first. At equal time stamps the
IMU sample is sent before the GNSS sample.
"""

from __future__ import annotations

import copy
import importlib
import json
import logging
import math
import os
import time
from collections import deque
from dataclasses import asdict

import numpy as np
import pymap3d

from .mavout import Encoder, LiveLink, TlogWriter
from .scenario import Scenario
from .sensors import Sensors
from .vehicle import Vehicle

log = logging.getLogger(__name__)

PHYSICS_STEP_US = 5000      # the vehicle is integrated at 200 Hz or finer
CAN_TIME_OFFSET_US = 1_000_000  # DroneCAN time stamps: the bus had run 1 s before the drive (0 means "unknown")


def sample_us(k: int, hz: float) -> int:
    """Time of sample k of a sensor at hz: round(k * 1e6 / hz) microseconds."""
    return int(round(k * 1e6 / hz))


def first_sample_at(t_us: int, hz: float) -> int:
    """Index of the first sample of a sensor at hz taken at or after t_us.

    Not ceil(t_us / round(1e6 / hz)): where 1e6 / hz is not a whole number of microseconds (3, 6, 7
    or 9 Hz) the rounded period drifts from the sample times and that ceiling comes out one too many.
    """
    k = max(0, math.floor(t_us * hz / 1e6) - 1)
    while sample_us(k, hz) < t_us:
        k += 1
    return k


def truth_record(scenario: Scenario, seed: int, sensors: Sensors, trajectory: dict) -> dict:
    """The ground truth written beside a tlog as NAME.truth.json (DESIGN.md, Contracts)."""

    def clean(obj):     # JSON has no infinity: an attack without an end lasts "until the end"
        return {k: ("end" if isinstance(v, float) and math.isinf(v) else v) for k, v in obj.items()}

    attacks = []
    for a in scenario.attacks:
        start_us = int(round(a.start_s * 1e6))
        attacks.append({"kind": a.kind, "sensor": a.sensor, "channel": a.channel, "magnitude": a.magnitude,
                        "start_time_usec": start_us,
                        "start_gnss_index": first_sample_at(start_us, scenario.rates.gnss_hz),
                        "duration_s": "end" if math.isinf(a.duration_s) else a.duration_s})
    return {
        "scenario": scenario.name,
        "description": scenario.description,
        "seed": seed,
        "duration_s": scenario.duration_s,
        "rates": asdict(scenario.rates),
        "noise": asdict(scenario.noise),
        "start": asdict(scenario.start),
        "route": clean(asdict(scenario.route)),
        "attacks": attacks,
        "drawn": {"gyro_bias_radps": sensors.gyro_bias.tolist(), "accel_bias_mps2": sensors.accel_bias.tolist()},
        "trajectory": trajectory,
    }


class Simulation:
    """One run of a scenario. Sinks get (t_us, message); `on_gnss` lets a CAN publisher ride along."""

    def __init__(self, scenario: Scenario, seed: int, autopilot: str = "ardupilot"):
        self.scenario = scenario
        self.seed = seed
        self.encoder = Encoder(autopilot)
        self.sensors = Sensors(scenario, seed)
        self.vehicle = Vehicle(scenario.route, scenario.start.heading_deg)
        self.trajectory = {"t_usec": [], "lat_deg": [], "lon_deg": [], "east_m": [], "north_m": [], "yaw_rad": [],
                           "speed_mps": []}
        self._true_en: list[tuple[float, float]] = []     # the truth's east, north at each fix: to latitude and
                                                          # longitude in one call when the truth is written
        # a receiver with latency reports the vehicle as it was gnss_delay_s ago: the states since then
        delay = scenario.noise.gnss_delay_s
        self.past = deque([(0.0, copy.copy(self.vehicle.s))]) if delay > 0 and scenario.rates.gnss_hz > 0 else None

    def ticks(self):
        """Yield (t_us, [messages]) in time order, advancing the vehicle between ticks.

        Sample k of a sensor at f Hz is taken at round(k * 1e6 / f) microseconds; the vehicle is
        integrated between consecutive sample times in steps of at most PHYSICS_STEP_US.
        """
        sc = self.scenario
        rates = {"heartbeat": sc.rates.heartbeat_hz, "imu": sc.rates.imu_hz, "gnss": sc.rates.gnss_hz}
        count = {name: 0 for name, hz in rates.items() if hz > 0}
        end_us = int(round(sc.duration_s * 1e6))
        fed = (0.0, 0.0, 0.0)       # the controller's position: last GNSS fix (east, north) and its time
        enc, veh = self.encoder, self.vehicle
        t_us = 0
        while t_us <= end_us:
            t_s, s, out = t_us / 1e6, veh.s, []
            due = [name for name in count if sample_us(count[name], rates[name]) == t_us]
            for name in due:        # in the order heartbeat, IMU, GNSS
                count[name] += 1
                if name == "heartbeat":
                    out.append(enc.heartbeat())
                elif name == "imu":
                    out.append(enc.raw_imu(t_us, self.sensors.imu(t_s, s)))
                else:
                    out.append(self._gnss(t_us, s))
                    fed = (self.last_gnss[0], self.last_gnss[1], t_s)
            yield t_us, out
            next_us = min(sample_us(count[name], rates[name]) for name in count)
            substeps = max(1, -(-(next_us - t_us) // PHYSICS_STEP_US))
            dt = (next_us - t_us) / substeps / 1e6
            for _ in range(substeps):
                # dead-reckon the fed fix by the vehicle's own odometry since it arrived
                age = t_s - fed[2]
                fe = fed[0] + age * s.v * math.cos(s.psi)
                fn = fed[1] + age * s.v * math.sin(s.psi)
                veh.step(dt, *veh.command(fe, fn))
                t_s += dt
                if self.past is not None:
                    self.past.append((t_s, copy.copy(veh.s)))
            t_us = next_us

    def _gnss(self, t_us: int, s):
        """One GNSS sample (and the truth beside it) as GPS_RAW_INT."""
        sc, st, n = self.scenario, self.scenario.start, self.scenario.noise
        seen = s
        if self.past is not None:      # the latest state no later than t - delay (at the physics step)
            then, past = t_us / 1e6 - n.gnss_delay_s + 1e-9, self.past
            while len(past) > 1 and past[1][0] <= then:
                past.popleft()
            seen = past[0][1]
        g = self.sensors.gnss(t_us / 1e6, seen)
        self.last_gnss = (g.east_m, g.north_m)
        lat, lon, alt = pymap3d.enu2geodetic(g.east_m, g.north_m, 0.0, st.lat_deg, st.lon_deg, st.alt_m)
        self._true_en.append((s.e, s.n))
        for key, value in (("t_usec", t_us), ("east_m", s.e), ("north_m", s.n), ("yaw_rad", s.psi), ("speed_mps", s.v)):
            self.trajectory[key].append(round(value, 9) if isinstance(value, float) else value)
        lost = any(a.kind == "dropout" and a.active(t_us / 1e6) for a in sc.attacks)
        # the accuracies the receiver reports (None: it reports none); never 0, which means "unknown"
        h_acc = max(n.gnss_h_acc_m, 0.001) if n.gnss_h_acc_reported else None
        vel_acc = max(n.gnss_vel_white_mps, 0.01) if n.gnss_vel_acc_reported else None
        return self.encoder.gps_raw_int(t_us, 0.0 if lost else lat, 0.0 if lost else lon, alt, g.vel_n_mps,
                                        g.vel_e_mps, h_acc, vel_acc, fix_type=1 if lost else 3)

    def truth(self) -> dict:
        st = self.scenario.start
        if len(self.trajectory["lat_deg"]) < len(self._true_en):     # the fixes since the last call
            e, n = np.array(self._true_en[len(self.trajectory["lat_deg"]):]).reshape(-1, 2).T
            lat, lon, _ = pymap3d.enu2geodetic(e, n, 0.0, st.lat_deg, st.lon_deg, st.alt_m)
            self.trajectory["lat_deg"] += [round(v, 9) for v in lat.tolist()]
            self.trajectory["lon_deg"] += [round(v, 9) for v in lon.tolist()]
        return truth_record(self.scenario, self.seed, self.sensors, self.trajectory)


# log formats the simulator writes besides tlog: keyword -> (module, writer class); each writer takes
# the simulator's MAVLink messages, send(t_us, msg), and writes them in its own format, then close()
LOG_WRITERS = {"bin": (".dataflash", "DataFlashWriter"), "ulg": (".ulog", "UlogWriter")}


def _log_writer(kind: str, path: str):
    module, cls = LOG_WRITERS[kind]
    return getattr(importlib.import_module(module, __package__), cls)(path)


def run(scenario: Scenario, seed: int, *, tlog: str | None = None, out: str | None = None,
        speedup: float = 1.0, fast: bool = False, on_statustext=None, can=None,
        bin: str | None = None, ulg: str | None = None, autopilot: str = "ardupilot", stream_hz: float = 0.0,
        on_request=None) -> dict:
    """Run a scenario to the end; returns the truth record (and writes NAME.truth.json beside each
    log file).

    `tlog` writes a tlog, `bin` an ArduPilot DataFlash log, `ulg` a PX4 ULog (any of them, the same
    run), `out` sends live MAVLink, `can` publishes DroneCAN; live output (MAVLink or
    CAN) is paced at `speedup` times real time unless `fast`; a tlog alone is written at once.
    `on_statustext(msg)` is called for every STATUSTEXT received on `out`.
    `can` is an object with send_gnss/send_imu/send_mag (guard_sim.canbus.CanPublisher) or None.
    `autopilot` "px4" sends the tlog's and the live link's IMU as PX4 does, HIGHRES_IMU (mavout.Encoder).
    `stream_hz` > 0: the live link sends GPS_RAW_INT and the IMU at most that often until asked for more,
    as an autopilot's port at its default rates; `on_request(name, interval_us)` for each request
    honoured (mavout.LiveLink).
    """
    sim = Simulation(scenario, seed, autopilot)
    writers = [TlogWriter(tlog, sim.encoder)] if tlog else []
    files = {k: p for k, p in (("bin", bin), ("ulg", ulg)) if p}
    writers += [_log_writer(k, p) for k, p in files.items()]
    link = LiveLink(out, sim.encoder, stream_hz, on_request) if out else None
    paced = (link is not None or can is not None) and not fast
    wall0 = time.monotonic()
    try:
        for t_us, messages in sim.ticks():
            if paced:
                target = wall0 + t_us / 1e6 / speedup
                while (remaining := target - time.monotonic()) > 0:
                    if link is None:
                        time.sleep(remaining)
                        break
                    msg = link.receive(min(remaining, 0.05))
                    if msg is not None and on_statustext:
                        on_statustext(msg)
            for msg in messages:
                for writer in writers:
                    writer.send(t_us, msg)
                if link:
                    link.send(t_us, msg)
                if can is not None:
                    _to_can(can, t_us, msg)
        if link is not None:    # a last moment for the monitor's answers
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                msg = link.receive(0.05)
                if msg is not None and on_statustext:
                    on_statustext(msg)
    finally:
        for writer in writers:
            writer.close()
        if link:
            link.close()
    truth = sim.truth()
    for path in (p for p in (tlog, bin, ulg) if p):
        stem = os.path.splitext(path)[0]
        with open(stem + ".truth.json", "w") as f:
            json.dump(truth, f, indent=1)
    return truth


def _to_can(can, t_us: int, msg) -> None:
    """Publish the same sample on a CAN bus as DroneCAN (units back from ArduPilot's)."""
    name = msg.get_type()
    t_us += CAN_TIME_OFFSET_US
    if name == "GPS_RAW_INT":
        speed, cog = msg.vel / 100.0, math.radians(msg.cog / 100.0)
        h_acc = msg.h_acc / 1000.0 if msg.h_acc else None      # 0: unknown, sent as no covariance
        can.send_gnss(t_us, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0, speed * math.cos(cog),
                      speed * math.sin(cog), 0.0, msg.fix_type >= 3, h_acc,
                      v_acc_m=msg.v_acc / 1000.0 if msg.v_acc else None,
                      vel_acc_mps=msg.vel_acc / 1000.0 if msg.vel_acc else None)
    elif name == "RAW_IMU":
        g = 9.80665
        can.send_imu(t_us, (msg.xacc * g / 1000, msg.yacc * g / 1000, msg.zacc * g / 1000),
                     (msg.xgyro / 1000, msg.ygyro / 1000, msg.zgyro / 1000))
        if not getattr(msg, "mag_held", False):     # a slower compass: each reading once (Encoder.raw_imu)
            can.send_mag(t_us, (msg.xmag / 1000, msg.ymag / 1000, msg.zmag / 1000))

