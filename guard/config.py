"""Configuration: one TOML file, validated once into frozen objects and passed down.

An unknown section or key, a wrong type or an impossible value is a ConfigError naming the file and
the key. Every key has a default; configs/guard.toml lists them all with their units.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace

import tomli_w

from guard import DEFAULT_CONFIG_PATH
from guard.core.monitor import MonitorConfig
from guard.core.detectors import DETECTORS, DetectorConfig
from guard.core.ekf import FilterConfig
from guard.errors import ConfigError


DEFAULT_PATH = DEFAULT_CONFIG_PATH          # read when no --config is given and it exists


@dataclass(frozen=True)
class LinkConfig:
    connect: str = "udpin:0.0.0.0:14550"    # pymavlink URL, or can:INTERFACE:CHANNEL
    system_id: int = 1                      # the autopilot's MAVLink system id (0: any)
    heartbeat_hz: float = 1.0
    statistic_hz: float = 2.0               # NAMED_VALUE_FLOAT of the test statistic
    link_timeout_s: float = 5.0             # warn when no GNSS or IMU message came for this long
    signing_key_file: str = ""              # MAVLink 2 signing: a file holding 32 bytes (or 64 hex digits)
    require_signed: bool = False            # with a key: reject unsigned incoming frames
    gcs: str = ""                           # a second link guard's STATUSTEXT, HEARTBEAT and grd_ratio go to as
                                            # well (udpout:HOST:PORT): a ground station behind a router that
                                            # forwards them only to the autopilot (MAVProxy); "" none
    request_rates: bool = True              # ask the autopilot for the streams read, at rates guard can use
                                            # (guard.sources.rates); false: ask nothing


@dataclass(frozen=True)
class CanConfig:
    gnss_node_id: int = 0                   # DroneCAN node ids; 0: the first node heard
    imu_node_id: int = 0
    time_source: str = "message"            # "message" (DroneCAN timestamp) or "receive"


@dataclass(frozen=True)
class LogConfig:
    mcap: str = ""                          # a .mcap file or a directory; "" writes no log
    rotate_mb: float = 256.0                # start a new file past this size (0: never)
    rotate_s: float = 3600.0                # or past this much vehicle time (0: never)
    chunk_kb: float = 256.0                 # a crash loses at most one chunk
    keep_mb: float = 2000.0                 # a directory's guard-*.mcap files, at most (the oldest go; 0: all kept)


@dataclass(frozen=True)
class Config:
    link: LinkConfig = field(default_factory=LinkConfig)
    can: CanConfig = field(default_factory=CanConfig)
    log: LogConfig = field(default_factory=LogConfig)
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    source_text: str = ""                   # the TOML as read, stored in the MCAP log


SIGNED = {"mag_offset_rad", "sensors_ahead_m"}     # keys whose sign means a direction (a compass off east or west,
                                                # sensors behind the axle): any finite number


def _typed(cls, table: dict, where: str):
    """Build dataclass `cls` from `table`, checking each key against its default's type."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table")
    defaults = cls()
    known = {f.name for f in fields(cls)}
    values = {}
    for key, value in table.items():
        name = f"{where}.{key}"
        if key not in known:
            raise ConfigError(f"{name}: unknown key (known: {', '.join(sorted(known))})")
        default = getattr(defaults, key)
        if key == "declination_deg":
            if value == "auto":
                value = None
            elif isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{name}: expected \"auto\" or a number of degrees, got {value!r}")
            values[key] = None if value is None else float(value)
            continue
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{name}: expected true or false, got {value!r}")
        elif isinstance(default, (int, float)):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{name}: expected a number, got {value!r}")
            if isinstance(default, int) and not isinstance(default, bool) and not float(value).is_integer():
                raise ConfigError(f"{name}: expected a whole number, got {value!r}")
            if not math.isfinite(value):
                raise ConfigError(f"{name}: must be a finite number, got {value!r}")
            if value < 0 and key not in SIGNED:
                raise ConfigError(f"{name}: must be a finite number >= 0, got {value!r}")
            value = type(default)(value)
        elif isinstance(default, tuple):
            if not isinstance(value, list) or not value or any(
                    isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 100 for v in value):
                raise ConfigError(f"{name}: expected a list of numbers in (0, 100), got {value!r}")
            value = tuple(float(v) for v in value)
        elif isinstance(default, str) and not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        values[key] = value
    return replace(defaults, **values)


def _check(cfg: Config, where: str) -> None:
    """Values that type-check but cannot work."""
    det, flt, link = cfg.monitor.detector, cfg.monitor.filter, cfg.link
    problems = {
        "detector.name": (det.name not in DETECTORS, f"must be one of {', '.join(DETECTORS)}"),
        "detector.false_alarm_interval_h": (det.false_alarm_interval_h <= 0, "must be > 0"),
        "detector.paper_warmup": (det.paper_warmup < 2, "must be >= 2"),
        "detector.gate_sigma": (det.gate_sigma <= 0, "must be > 0"),
        "detector.shock_sigma": (0 < det.shock_sigma <= max(det.shift_sigma, default=0.0),
                                 "must be 0 (no bound) or above the largest of detector.shift_sigma "
                                 "(at or below it, a large shift never accumulates)"),
        "link.system_id": (link.system_id > 255, "must be 0..255"),
        "link.heartbeat_hz": (link.heartbeat_hz <= 0, "must be > 0"),
        "can.gnss_node_id": (cfg.can.gnss_node_id > 127, "must be 0..127"),
        "can.imu_node_id": (cfg.can.imu_node_id > 127, "must be 0..127"),
        "can.time_source": (cfg.can.time_source not in ("message", "receive"), "must be \"message\" or \"receive\""),
        "monitor.readmit_s": (cfg.monitor.readmit_s <= 0, "must be > 0"),
        "filter.gnss_delay_s": (flt.gnss_delay_s > 1.0, "must be at most 1 s (receivers lag 0.05 to 0.25 s)"),
        "filter.gnss_latency_sigma_s": (not 0 <= flt.gnss_latency_sigma_s <= 1.0, "must be within 0..1 s"),
        "filter.gnss_latency_sigma_air_s": (not 0 <= flt.gnss_latency_sigma_air_s <= 1.0, "must be within 0..1 s"),
        "filter.mag_offset_per_turn_rad": (not 0 <= flt.mag_offset_per_turn_rad <= 0.5, "must be within 0..0.5 rad"),
        "filter.mag_offset_rad": (abs(flt.mag_offset_rad) > math.pi, "must be within -pi..pi rad"),
        "monitor.vehicle": (cfg.monitor.vehicle not in ("auto", "ground", "air"),
                            "must be \"auto\", \"ground\" or \"air\""),
        # values that would switch detection off, or flood the disk
        "monitor.max_gap_s": (cfg.monitor.max_gap_s < 1.0, "must be >= 1 s (below, every gap restarts the filter)"),
        "monitor.readmit_sigma": (cfg.monitor.readmit_sigma < 1.0,
                                  "must be >= 1 (below, no sensor is ever re-admitted)"),
        "monitor.max_coast_m": (cfg.monitor.max_coast_m < 1.0, "must be >= 1 m"),
        "monitor.max_coast_heading_deg": (not 1.0 <= cfg.monitor.max_coast_heading_deg <= 90.0,
                                          "must be within 1..90 deg"),
        "monitor.min_imu_hz": (cfg.monitor.min_imu_hz > 100.0, "must be at most 100 Hz"),
        "monitor.max_wander_factor": (not 1.0 <= cfg.monitor.max_wander_factor <= 10.0,
                                      "must be within 1..10 (1: each test as the model says)"),
        "filter.q_pos_m": (flt.q_pos_m <= 0, "must be > 0 (at 0 the estimate cannot follow the GNSS's slow error)"),
        "filter.gnss_pos_acc_fraction": (not 0 < flt.gnss_pos_acc_fraction <= 1, "must be in (0, 1]"),
        "filter.q_accel_no_imu_mps2": (flt.q_accel_no_imu_mps2 <= 0, "must be > 0"),
        "filter.slip_rad_per_mps2": (not 0 <= flt.slip_rad_per_mps2 <= 0.05,
                                     "must be within 0..0.05 (a car on tarmac: 0.005 to 0.01)"),
        "filter.sensors_ahead_m": (not -3.0 <= flt.sensors_ahead_m <= 3.0,
                                   "must be within -3..3 m (a car's wheelbase is 2.5 to 3 m)"),
        "log.rotate_mb": (0 < cfg.log.rotate_mb < 1.0, "must be 0 (never) or >= 1 MB"),
        "link.require_signed": (link.require_signed and not link.signing_key_file,
                                "needs link.signing_key_file (without a key no signature can be checked)"),
    }
    for f in fields(FilterConfig):
        value = getattr(flt, f.name)
        if f.name.endswith(("_sigma_m", "_sigma_mps", "_sigma_rad", "_sigma_radps", "_sigma_mps2", "_unreported_m",
                            "_unreported_mps")) and value <= 0:
            problems[f"filter.{f.name}"] = (True, "must be > 0")
    for key, (bad, why) in problems.items():
        if bad:
            raise ConfigError(f"{where}: {key}: {why}")


def parse(data: dict, where: str = "config", text: str = "") -> Config:
    sections = {
        "link": LinkConfig, "can": CanConfig, "log": LogConfig,
        "filter": FilterConfig, "detector": DetectorConfig, "monitor": MonitorConfig,
    }
    built = {}
    for key, table in data.items():
        if key not in sections:
            raise ConfigError(f"{where}: {key}: unknown section (known: {', '.join(sections)})")
        if key == "monitor":
            table = {k: v for k, v in table.items()} if isinstance(table, dict) else table
            for nested in ("filter", "detector"):
                if isinstance(table, dict) and nested in table:
                    raise ConfigError(f"{where}: monitor.{nested}: write it as its own [{nested}] section")
        built[key] = _typed(sections[key], table, f"{where}: {key}")
    monitor = built.pop("monitor", MonitorConfig())
    monitor = replace(monitor, filter=built.pop("filter", FilterConfig()),
                      detector=built.pop("detector", DetectorConfig()))
    cfg = Config(monitor=monitor, source_text=text, **built)
    _check(cfg, where)
    return cfg


def load(path: str | None) -> Config:
    """Read and validate a config file (None: DEFAULT_PATH if it exists, else all defaults)."""
    path = path or default_path()
    if path is None:
        return Config()
    data, text = read(path)
    return parse(data, path, text)


def default_path() -> str | None:
    """The config file read when none is given: DEFAULT_PATH, where it exists."""
    return DEFAULT_PATH if os.path.exists(DEFAULT_PATH) else None


def table(cfg: Config) -> dict:
    """The whole configuration in effect, defaults included, as the TOML table a file would hold
    (the sections of configs/guard.toml; an unset declination_deg is written "auto")."""
    monitor = {f.name: getattr(cfg.monitor, f.name) for f in fields(MonitorConfig)
               if f.name not in ("filter", "detector")}
    out = {"link": asdict(cfg.link), "can": asdict(cfg.can), "log": asdict(cfg.log),
           "monitor": monitor, "filter": asdict(cfg.monitor.filter), "detector": asdict(cfg.monitor.detector)}
    if out["monitor"]["declination_deg"] is None:
        out["monitor"]["declination_deg"] = "auto"
    return out


def dump(cfg: Config) -> str:
    """table(cfg) as TOML text: what `guard config` prints and the MCAP log stores; parse() reads it
    back to the same configuration."""
    return tomli_w.dumps(table(cfg))


def read(path: str) -> tuple[dict, str]:
    """A config file's TOML table and text, not yet validated; ConfigError names the file."""
    try:
        with open(path, "rb") as f:
            text = f.read().decode()
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not UTF-8 text") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: {e}") from None
    return data, text
