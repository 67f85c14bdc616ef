"""What a source's samples and the core's events promise, whatever bytes came in.

A sample (guard.model.samples) leaves an edge in SI units with an integer time stamp, every float
finite, every value inside the envelope below: the widest range any edge documents (MAVLink's wire
types, the DataFlash, ULog and CAN readers' plausibility limits). A position is finite, and on the
globe with a 3D fix; an altitude is any finite number (a ULog's is a float64). The core is fuzzed with
samples anywhere inside this envelope (`guard.core` must take all of them), and each decoder's output
is checked against it. Counters (`messages`, `skipped`) are counts by name, and what a reader says
(notes, verdicts) goes into a JSON report without NaN.
"""

from __future__ import annotations

import json
import math

import numpy as np

from guard.model.events import Estimate, Tested
from guard.model.samples import Attitude, GnssFix, ImuSample, VehicleType

T_MAX_US = 4_102_444_800_000_000    # 2100-01-01 in unix microseconds (guard.sources.mavlink.T_MAX_US)
SPEED_MAX_MPS = 700.0               # |ground velocity| per axis: GPS_RAW_INT's u16 cm/s reaches 655 m/s
ACC_MAX_MPS2, GYRO_MAX_RADPS = 2000.0, 200.0    # the DataFlash reader's limits, the widest
MAG_MAX_GAUSS = 100.0               # RAW_IMU's and DataFlash's int16 mGauss reach 32.8 G
ACCURACY_MAX = 2e19                 # h_acc m, vel_acc m/s: the root of DroneCAN's largest float32 variance
ROLL_MAX_RAD, PITCH_MAX_RAD = math.pi + 1e-6, 1.5   # float32(pi) is 8.7e-8 above pi


class Broken(AssertionError):
    """A promise of a sample, an event or a reader's account is broken."""


def _need(ok: bool, what: str, thing) -> None:
    if not ok:
        raise Broken(f"{what}: {thing!r}")


def _finite(x, limit: float) -> bool:
    return isinstance(x, float | int) and not isinstance(x, bool) and math.isfinite(x) and abs(x) <= limit


def _time(t_us) -> bool:
    return type(t_us) is int and 0 <= t_us <= T_MAX_US


def check_sample(s) -> None:
    """Raise Broken unless `s` is a sample inside the envelope."""
    if type(s) is GnssFix:
        _need(_time(s.t_us), "GnssFix time", s)
        _need(type(s.fix_ok) is bool, "GnssFix fix_ok not a bool", s)
        _need(all(_finite(v, math.inf) for v in (s.lat_deg, s.lon_deg, s.alt_m)), "GnssFix position not finite", s)
        if s.fix_ok:
            _need(abs(s.lat_deg) <= 90 and abs(s.lon_deg) <= 180 and (s.lat_deg, s.lon_deg) != (0.0, 0.0),
                  "GnssFix position off the globe", s)
        _need((s.vel_n_mps is None) == (s.vel_e_mps is None), "GnssFix velocity half given", s)
        for v in (s.vel_n_mps, s.vel_e_mps):
            _need(v is None or _finite(v, SPEED_MAX_MPS), "GnssFix velocity", s)
        for a in (s.h_acc_m, s.vel_acc_mps):
            _need(a is None or (_finite(a, ACCURACY_MAX) and a >= 0), "GnssFix accuracy", s)
    elif type(s) is ImuSample:
        _need(_time(s.t_us), "ImuSample time", s)
        _need(all(_finite(a, ACC_MAX_MPS2) for a in (s.acc_x_mps2, s.acc_y_mps2, s.acc_z_mps2)),
              "ImuSample acceleration", s)
        _need(all(_finite(w, GYRO_MAX_RADPS) for w in (s.gyro_x_radps, s.gyro_y_radps, s.gyro_z_radps)),
              "ImuSample rate", s)
        mag = (s.mag_x_gauss, s.mag_y_gauss, s.mag_z_gauss)
        _need(mag == (None, None, None) or all(_finite(m, MAG_MAX_GAUSS) for m in mag), "ImuSample magnetometer", s)
    elif type(s) is Attitude:
        _need(_time(s.t_us), "Attitude time", s)
        _need(_finite(s.roll_rad, ROLL_MAX_RAD) and _finite(s.pitch_rad, PITCH_MAX_RAD), "Attitude angles", s)
    elif type(s) is VehicleType:
        _need(type(s.ground) is bool, "VehicleType ground not a bool", s)
    else:
        raise Broken(f"not a sample: {s!r}")


def check_account(reader) -> None:
    """A reader's counts are counts by name, its notes and verdicts a JSON report's."""
    for counter in ("messages", "skipped"):
        counts = getattr(reader, counter)
        _need(all(isinstance(k, str) and type(n) is int and n > 0 for k, n in counts.items()),
              f"{counter} not positive counts by name", dict(counts))
    _need(all(isinstance(n, str) for n in getattr(reader, "notes", [])), "notes not text", reader.notes)
    try:
        json.dumps([getattr(reader, "verdicts", []), getattr(reader, "notes", [])], allow_nan=False)
    except (TypeError, ValueError) as e:
        raise Broken(f"verdicts or notes not JSON: {e}") from None


def check_events(events) -> None:
    """The core's events: estimates and test statistics finite."""
    for e in events:
        if type(e) is Estimate:
            _need(bool(np.isfinite(e.x).all() and np.isfinite(e.P_diag).all())
                  and math.isfinite(e.east_m) and math.isfinite(e.north_m), "Estimate not finite", e)
            _need(bool((e.P_diag >= 0).all()), "Estimate with a negative variance", e)
        elif type(e) is Tested:
            _need(all(math.isfinite(v) for v in e.statistic), "Tested statistic not finite", e)
