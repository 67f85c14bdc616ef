"""Scenario files: TOML under configs/scenarios/ (installed as the package data of guard_sim.scenarios),
validated into frozen dataclasses.

A scenario names the route, the sensor rates, the noise of each sensor (1-sigma, in SI units) and
the attacks. Unknown keys, wrong types and impossible values are errors that name the file and key.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path

# the shipped scenarios, wherever the package is installed (configs/scenarios/ in the repository)
SCENARIO_DIR = resources.files(f"{__package__}.scenarios")

ATTACK_KINDS = {
    "step": "adds `magnitude` from start_s on",
    "ramp": "adds magnitude * (t - start_s): a slow drift, magnitude per second",
    "bias": "a constant offset on an IMU channel (gyro rad/s, accel m/s^2)",
    "freeze": "GNSS position and velocity stop updating while the vehicle moves (magnitude unused)",
    "spoof": "coordinated GNSS spoof: position drifts as magnitude*(t-s)^2/2 and velocity as magnitude*(t-s)",
    "dropout": "a fault, not an attack: the receiver reports no fix for duration_s (magnitude unused)",
}
SENSOR_CHANNELS = {
    "gnss_pos": ("north", "east"),
    "gnss_vel": ("north", "east"),
    "gyro": ("x", "y", "z"),
    "accel": ("x", "y", "z"),
    "mag": ("x", "y", "z"),
}


class ScenarioError(Exception):
    """A scenario cannot be loaded; the message names the file and the key."""


@dataclass(frozen=True)
class Start:
    lat_deg: float = 40.4237
    lon_deg: float = -86.9212
    alt_m: float = 187.0
    heading_deg: float = 0.0        # compass heading: 0 = north, clockwise
    year: float = 2026.0            # date of the World Magnetic Model's field (decimal year)


@dataclass(frozen=True)
class Route:
    waypoints_m: tuple = ((0.0, 0.0), (100.0, 0.0))   # (east, north[, speed_mps]) from the start
    speed_mps: float = 5.0          # cruise speed where a waypoint gives none
    loop: bool = False              # start again at the first waypoint
    max_accel_mps2: float = 1.0
    max_yaw_rate_radps: float = 0.6
    max_yaw_accel_radps2: float = 2.0    # how fast the yaw rate may change (times the speed: the lateral jerk)
    max_yaw_jerk_radps3: float = 0.0     # how fast the yaw acceleration may change; 0: it steps (vehicle.py)
    lookahead_m: float = 6.0
    sideslip_rad_per_mps2: float = 0.0   # a wheel's slip: the course turns outward of the heading by this
                                         # much per m/s^2 of lateral acceleration (a car: 0.005 to 0.01)
    sensors_ahead_m: float = 0.0         # the IMU and the GNSS antenna this far ahead of the point that does
                                         # not slide sideways (a car's rear axle, a skid-steer's turning centre;
                                         # < 0: behind it): in a turn they move sideways at this times the yaw rate


@dataclass(frozen=True)
class Rates:
    imu_hz: float = 50.0
    gnss_hz: float = 10.0
    heartbeat_hz: float = 1.0       # 0: no heartbeat


@dataclass(frozen=True)
class Noise:
    """1-sigma sensor errors, and the fixed errors of this vehicle's sensors.

    Biases are drawn once per run from N(0, sigma^2). Yaw angles are about the body z axis (FRD, z
    down), positive clockwise seen from above, the sense in which the compass heading grows (north 0,
    east 90): a sensor yawed by a reads R_z(a)^T v of a body vector v, (x cos a + y sin a,
    -x sin a + y cos a, z). So with `mag_offset_deg` = a the magnetometer's x axis points a to the
    right of the nose and its heading atan2(-m_y, m_x) reads the true heading + a; with
    `imu_yaw_mount_deg` = a a forward acceleration f shows as (f cos a, -f sin a) on the
    accelerometer's x and y. Scale-factor errors multiply the true specific force and rate (all three
    axes) by 1 + scale before bias and noise are added.
    """

    gnss_pos_white_m: float = 0.3
    gnss_pos_markov_m: float = 0.7        # first-order Gauss-Markov error: steady-state sigma
    gnss_pos_markov_tau_s: float = 60.0   # and correlation time
    gnss_vel_white_mps: float = 0.05
    gnss_h_acc_m: float = 0.8             # what the receiver reports as its accuracy: sqrt(0.3^2 + 0.7^2)
    gnss_delay_s: float = 0.0             # the receiver's latency: a fix shows the vehicle this long before its
                                          # time stamp
    gyro_white_radps: float = 0.003
    gyro_bias_radps: float = 0.002
    accel_white_mps2: float = 0.05
    accel_bias_mps2: float = 0.05
    mag_white_gauss: float = 0.004
    # this vehicle's own sensors (the defaults are the ideal ones); angles as in the docstring
    mag_offset_deg: float = 0.0           # compass heading error, east positive: heading read = true + this
    mag_wander_deg: float = 0.0           # and a heading error that comes and goes (a multicopter's motors' and
    mag_wander_tau_s: float = 3.0         # wiring's field): first-order Gauss-Markov, its sigma and correlation time
    mag_iron_x: float = 0.0               # a hard iron: a field fixed to the body, forward and right, as a fraction
    mag_iron_y: float = 0.0               # of the horizontal field (0.35: a heading up to 20 degrees off, by heading)
    accel_scale: float = 0.0              # scale-factor error: 0.02 reads 2 % high (applied before bias, noise)
    gyro_scale: float = 0.0               # likewise for the rate
    imu_yaw_mount_deg: float = 0.0        # accelerometer and gyro (not the compass) mounted yawed by this
    gnss_h_acc_reported: bool = True      # false: GPS_RAW_INT's h_acc and v_acc are 0 ("unknown")
    gnss_vel_acc_reported: bool = True    # false: its vel_acc is 0 ("unknown"); true: gnss_vel_white_mps
    gnss_course_hold_mps: float = 0.0     # below this measured speed the receiver holds its last course over
                                          # ground (real ones do, where the course means nothing: 0.3 to 2 m/s)
    mag_hz: float = 0.0                   # the compass's own rate: 0 reads it with every IMU sample; slower, each
                                          # reading is held until the next, and RAW_IMU repeats it meanwhile (as an
                                          # autopilot's does: real compasses read at 10 to 100 Hz); 1 to 400 Hz


MAX_WANDER_DEG = 30.0       # the compass's wander (1 sigma): as far as its fixed offset may go
# noise keys that may be negative, with their limits (|value| <= limit); the others must be >= 0
SIGNED_NOISE = {"mag_offset_deg": 30.0, "accel_scale": 0.2, "gyro_scale": 0.2, "imu_yaw_mount_deg": 30.0,
                "mag_iron_x": 0.5, "mag_iron_y": 0.5}


@dataclass(frozen=True)
class Attack:
    kind: str
    sensor: str
    channel: str
    magnitude: float = 0.0
    start_s: float = 0.0
    duration_s: float = math.inf

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str = ""
    duration_s: float = 60.0
    start: Start = field(default_factory=Start)
    route: Route = field(default_factory=Route)
    rates: Rates = field(default_factory=Rates)
    noise: Noise = field(default_factory=Noise)
    attacks: tuple[Attack, ...] = ()


def _section(cls, data: dict, where: str):
    """Build dataclass `cls` from a TOML table, naming any unknown key or wrong type."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{where}: expected a table")
    known = {f.name: f for f in fields(cls)}
    for key in data:
        if key not in known:
            raise ScenarioError(f"{where}.{key}: unknown key (known: {', '.join(known)})")
    values = {}
    for key, value in data.items():
        default = getattr(cls, key, None) if key in cls.__dataclass_fields__ else None
        if isinstance(default, bool) or known[key].type == "bool":
            if not isinstance(value, bool):
                raise ScenarioError(f"{where}.{key}: expected true or false, got {value!r}")
        elif isinstance(default, float) or known[key].type == "float":
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ScenarioError(f"{where}.{key}: expected a number, got {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise ScenarioError(f"{where}.{key}: must be a finite number, got {value!r}")
        elif known[key].type == "str" and not isinstance(value, str):
            raise ScenarioError(f"{where}.{key}: expected a string, got {value!r}")
        values[key] = value
    return cls(**values)


def _route(data: dict, where: str) -> Route:
    route = _section(Route, {k: v for k, v in data.items() if k != "waypoints_m"}, where)
    raw = data.get("waypoints_m", Route.waypoints_m)
    points = []
    for i, p in enumerate(raw):
        ok = isinstance(p, (list, tuple)) and len(p) in (2, 3) and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) for c in p)
        if not ok:
            raise ScenarioError(f"{where}.waypoints_m[{i}]: expected [east_m, north_m] or [east_m, north_m, speed_mps]")
        points.append(tuple(float(c) for c in p))
    if len(points) < 2:
        raise ScenarioError(f"{where}.waypoints_m: needs at least two waypoints")
    return Route(**{**route.__dict__, "waypoints_m": tuple(points)})


def _attack(data: dict, where: str) -> Attack:
    if data.get("duration_s") == "end":     # the default: until the end of the run
        data = {k: v for k, v in data.items() if k != "duration_s"}
    for key in ("kind", "sensor", "channel"):
        if key not in data:
            raise ScenarioError(f"{where}.{key}: missing")
    a = _section(Attack, {k: v for k, v in data.items() if k != "magnitude"}, where)
    magnitude = data.get("magnitude", 0.0)
    if isinstance(magnitude, bool) or not isinstance(magnitude, (int, float)) or not math.isfinite(magnitude):
        raise ScenarioError(f"{where}.magnitude: expected a finite number, got {magnitude!r}")
    if a.kind not in ATTACK_KINDS:
        raise ScenarioError(f"{where}.kind: {a.kind!r} is not one of {', '.join(ATTACK_KINDS)}")
    if a.sensor not in SENSOR_CHANNELS:
        raise ScenarioError(f"{where}.sensor: {a.sensor!r} is not one of {', '.join(SENSOR_CHANNELS)}")
    if a.channel not in SENSOR_CHANNELS[a.sensor]:
        raise ScenarioError(f"{where}.channel: {a.channel!r} is not a channel of {a.sensor}")
    gnss = a.sensor.startswith("gnss")
    if a.kind in ("freeze", "spoof", "dropout") and not gnss or a.kind == "bias" and gnss:
        raise ScenarioError(f"{where}.kind: {a.kind!r} does not apply to sensor {a.sensor!r}")
    return Attack(**{**a.__dict__, "magnitude": float(magnitude)})


def parse(data: dict, where: str) -> Scenario:
    """Validate a scenario table (as read from TOML); `where` names its file in errors."""
    data = dict(data)
    top = {k: data.pop(k) for k in ("name", "description", "duration_s") if k in data}
    if "name" not in top:
        raise ScenarioError(f"{where}: name: missing")
    sections = {
        "start": lambda d, w: _section(Start, d, w),
        "route": _route,
        "rates": lambda d, w: _section(Rates, d, w),
        "noise": lambda d, w: _section(Noise, d, w),
    }
    built = {}
    for key, value in data.items():
        if key == "attack":
            if not isinstance(value, list):
                raise ScenarioError(f"{where}: attack: expected [[attack]] tables")
            built["attacks"] = tuple(_attack(a, f"{where}: attack[{i}]") for i, a in enumerate(value))
        elif key in sections:
            built[key] = sections[key](value, f"{where}: {key}")
        else:
            raise ScenarioError(f"{where}: {key}: unknown key")
    scenario = _section(Scenario, top, where)
    scenario = Scenario(**{**scenario.__dict__, **built})
    r = scenario.rates
    if not 10 <= r.imu_hz <= 400:
        raise ScenarioError(f"{where}: rates.imu_hz: must be within 10..400 Hz, got {r.imu_hz}")
    if not 1 <= r.gnss_hz <= 20:
        raise ScenarioError(f"{where}: rates.gnss_hz: must be within 1..20 Hz, got {r.gnss_hz}")
    if not 0 <= r.heartbeat_hz <= 10:
        raise ScenarioError(f"{where}: rates.heartbeat_hz: must be within 0..10 Hz (0: none), got {r.heartbeat_hz}")
    for name, value in scenario.noise.__dict__.items():
        if isinstance(value, bool):
            continue
        if name in SIGNED_NOISE:
            if abs(value) > SIGNED_NOISE[name]:
                raise ScenarioError(f"{where}: noise.{name}: must be within -{SIGNED_NOISE[name]:g}.."
                                    f"{SIGNED_NOISE[name]:g}, got {value}")
        elif value < 0:
            raise ScenarioError(f"{where}: noise.{name}: must be >= 0, got {value}")
    if scenario.noise.mag_hz and not 1 <= scenario.noise.mag_hz <= 400:
        # a compass slower than 1 Hz holds one reading for seconds: no compass a vehicle steers by
        raise ScenarioError(f"{where}: noise.mag_hz: must be 0 (with every IMU sample) or within 1..400 Hz, "
                            f"got {scenario.noise.mag_hz}")
    if scenario.noise.mag_wander_deg > MAX_WANDER_DEG:
        raise ScenarioError(f"{where}: noise.mag_wander_deg: must be within 0..{MAX_WANDER_DEG:g}, "
                            f"got {scenario.noise.mag_wander_deg}")
    if scenario.noise.mag_wander_deg > 0 and scenario.noise.mag_wander_tau_s <= 0:
        raise ScenarioError(f"{where}: noise.mag_wander_tau_s: must be > 0 with a mag_wander_deg, "
                            f"got {scenario.noise.mag_wander_tau_s}")
    for a in scenario.attacks:
        if a.start_s < 0 or a.duration_s <= 0:
            raise ScenarioError(f"{where}: attack: start_s must be >= 0 and duration_s > 0")
    st, route = scenario.start, scenario.route
    if not (-90 <= st.lat_deg <= 90 and -180 <= st.lon_deg <= 180):
        raise ScenarioError(f"{where}: start: latitude must be within -90..90 and longitude -180..180")
    if not 2025.0 <= st.year <= 2030.0:
        raise ScenarioError(f"{where}: start.year: the magnetic model covers 2025..2030, got {st.year}")
    for key in ("lookahead_m", "max_accel_mps2", "max_yaw_rate_radps", "max_yaw_accel_radps2"):
        if getattr(route, key) <= 0:
            raise ScenarioError(f"{where}: route.{key}: must be > 0")
    if route.max_yaw_jerk_radps3 < 0:
        raise ScenarioError(f"{where}: route.max_yaw_jerk_radps3: must be >= 0 (0: the yaw acceleration steps)")
    if not 0 <= route.sideslip_rad_per_mps2 <= 0.05:
        raise ScenarioError(f"{where}: route.sideslip_rad_per_mps2: must be within 0..0.05 (a car: 0.005 to 0.01)")
    if not -3.0 <= route.sensors_ahead_m <= 3.0:
        raise ScenarioError(f"{where}: route.sensors_ahead_m: must be within -3..3 m (a car's wheelbase is 2.5 to 3)")
    if route.speed_mps < 0 or any(len(p) == 3 and p[2] < 0 for p in route.waypoints_m):
        raise ScenarioError(f"{where}: route: speeds must be >= 0")
    if scenario.duration_s <= 0:
        raise ScenarioError(f"{where}: duration_s: must be > 0")
    return scenario


def load(name_or_path: str) -> Scenario:
    """Load a scenario by name (one of names(), shipped with the simulator) or by path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = SCENARIO_DIR / f"{name_or_path}.toml"
    if not path.is_file():
        known = ", ".join(names())
        raise ScenarioError(f"unknown scenario {name_or_path!r} (no file {path}; known: {known})")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{path}: {e}") from None
    return parse(data, str(path))


def names() -> list[str]:
    """The shipped scenarios' names."""
    return sorted(p.name.removesuffix(".toml") for p in SCENARIO_DIR.iterdir() if p.name.endswith(".toml"))
