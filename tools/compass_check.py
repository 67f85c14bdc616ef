"""A PX4 flight's compass against the autopilot's own yaw: where guard's magnetometer alarms come from.

    python tools/compass_check.py FLIGHT.ulg [FLIGHT.ulg ...]

For each log: the heading of its calibrated compass (vehicle_magnetometer), levelled with PX4's own
roll and pitch, plus the World Magnetic Model's declination at its first fix on its day, less PX4's
yaw (vehicle_attitude), as guard's heading test sees a compass; on the
ground before the motors draw current, and in flight (its range and rms, and its correlation with the
battery current: the motors' field). Then the same with PX4's learnt body field (EKF2's mag_B states,
estimator_states 19 to 21: the hard iron it keeps learning in flight) taken out, and guard's
magnetometer alarms on the log as it is and with that field taken out. What remains after it is
what a heading offset cannot learn.

Needs the topics vehicle_magnetometer, vehicle_attitude, estimator_states and battery_status; a log
without one is named with what it lacks and skipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from pyulog import ULog

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from guard.core.geo import WMM_EPOCH, declination_rad  # noqa: E402
from guard.model.samples import GnssFix, ImuSample    # noqa: E402
from guard.sources import open_log                   # noqa: E402
from guard.runtime.replay import replay              # noqa: E402

TOPICS = ("vehicle_magnetometer", "vehicle_attitude", "estimator_states", "battery_status")
FLYING_A = 2.0          # A: the motors draw more than this: in flight (or about to be)


def euler(att) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    q0, q1, q2, q3 = (att[f"q[{i}]"] for i in range(4))
    roll = np.arctan2(2 * (q0 * q1 + q2 * q3), 1 - 2 * (q1 ** 2 + q2 ** 2))
    pitch = np.arcsin(np.clip(2 * (q0 * q2 - q3 * q1), -1, 1))
    yaw = np.arctan2(2 * (q0 * q3 + q1 * q2), 1 - 2 * (q2 ** 2 + q3 ** 2))
    return roll, pitch, yaw


def declination(path: str) -> float:
    """The World Magnetic Model's declination (rad, east positive) at the log's first fix, on its day:
    what guard adds to a compass's heading (guard.core.aiding.imu.heading)."""
    source = open_log(path)
    try:
        fix = next((s for s in source.samples() if isinstance(s, GnssFix) and s.fix_ok), None)
    finally:
        source.close()
    return 0.0 if fix is None else declination_rad(fix.lat_deg, fix.lon_deg, fix.alt_m, source.date or WMM_EPOCH)


def heading_less_yaw(m: np.ndarray, roll, pitch, yaw, dec: float = 0.0) -> np.ndarray:
    """Degrees, wrapped: the levelled field's heading (FRD, NED yaw) plus the declination `dec` (rad)
    less the autopilot's yaw."""
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    xh = cp * m[:, 0] + sp * sr * m[:, 1] + sp * cr * m[:, 2]
    yh = cr * m[:, 1] - sr * m[:, 2]
    return (np.degrees(np.arctan2(-yh, xh) + dec - yaw) + 180.0) % 360.0 - 180.0


def at(t_of: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.minimum(np.searchsorted(t_of, t), len(t_of) - 1)


def without_field(b: np.ndarray):
    def inject(samples):
        for s in samples:
            if isinstance(s, ImuSample) and s.mag_x_gauss is not None:
                s = dataclasses.replace(s, mag_x_gauss=s.mag_x_gauss - b[0], mag_y_gauss=s.mag_y_gauss - b[1],
                                        mag_z_gauss=s.mag_z_gauss - b[2])
            yield s
    return inject


def check(path: str) -> str:
    try:
        log = ULog(path, list(TOPICS))
    except Exception as e:      # pyulog's own errors are of many kinds; the log is named and skipped
        return f"{path}: skipped, not a readable ULog ({type(e).__name__}: {e})"
    d = {x.name: x.data for x in log.data_list if x.multi_id == 0}
    missing = [name for name in TOPICS if name not in d]
    if missing:
        return f"{path}: skipped, it does not log {', '.join(missing)}"
    mag, att, st, bat = (d[n] for n in TOPICS)
    t = mag["timestamp"]
    m = np.column_stack([mag[f"magnetometer_ga[{i}]"] for i in range(3)])
    i = at(att["timestamp"], t)
    roll, pitch, yaw = (a[i] for a in euler(att))
    current = bat["current_a"][at(bat["timestamp"], t)]
    field = np.column_stack([st[f"states[{k}]"] for k in (19, 20, 21)])
    dec = declination(path)
    raw = heading_less_yaw(m, roll, pitch, yaw, dec)
    learnt = heading_less_yaw(m - field[-1], roll, pitch, yaw, dec)
    ground, air = current <= FLYING_A, current > FLYING_A
    if not air.any() or not ground.any():
        return f"{path}: skipped, no stretch both on the ground and in flight by its battery current"
    alarms = [Counter(str(a["sensor"]) for a in replay(path, inject=inj)["alarms"])["mag"]
              for inj in (None, without_field(field[-1]))]
    return "\n".join([
        f"{path}: (declination {math.degrees(dec):+.1f} deg)",
        f"  compass heading less the autopilot's yaw, on the ground: median {np.median(raw[ground]):+.1f} deg",
        f"  in flight: {raw[air].min():+.1f} to {raw[air].max():+.1f} deg, rms about its mean "
        f"{raw[air].std():.1f} deg, correlation with the current {np.corrcoef(raw[air], current[air])[0, 1]:+.2f}",
        f"  the autopilot's learnt body field {[round(float(v), 3) for v in field[-1]]} G taken out: in flight rms "
        f"{learnt[air].std():.1f} deg, correlation with the current "
        f"{np.corrcoef(learnt[air], current[air])[0, 1]:+.2f}",
        f"  guard's magnetometer alarms: {alarms[0]} as logged, {alarms[1]} with that field taken out"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", help="PX4 ULog files")
    args = ap.parse_args(argv)
    for path in args.logs:
        print(check(path))
    return 0


if __name__ == "__main__":
    sys.exit(main())
