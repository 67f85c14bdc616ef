"""What the autopilot's own log says where guard raised an alarm: was the inconsistency in the data?

    python tools/autopilot_view.py FLIGHT.bin                 # every alarm of `guard replay FLIGHT.bin`
    python tools/autopilot_view.py FLIGHT.ulg --at 24         # a PX4 log alike
    python tools/autopilot_view.py FLIGHT.bin --at 260.1      # a time of the log (s), alarm or not
    python tools/autopilot_view.py FLIGHT.bin --window 4 --json view.json

An ArduPilot DataFlash log carries its EKF's own GNSS velocity innovations (XKF3 for EKF3, NKF3 for
EKF2, EKF3 for EKF1: IVN, IVE, in m/s) and the IMU's vibration (VIBE: VibeX..Z in m/s/s, Clip); a
PX4 ULog its EKF2's (estimator_innovations: gps_hvel[0] north, [1] east, m/s) and the first IMU's
vibration (vehicle_imu_status: accel_vibration_metric in m/s, gyro_vibration_metric in rad/s, both
PX4's high-frequency levels of the IMU's deltas, and accel_clipping); a PX4 log of before 1.11 (2020)
the same under older names (ekf2_innovations: vel_pos_innov[0] north, [1] east; estimator_status:
vibe[2] the delta velocity's level in m/s, vibe[1] the delta angle's in rad, no clipping). For
each time asked (by default each alarm of guard's replay), over the `--window` seconds before it:
the mean of the autopilot's velocity innovations north and east, and where that mean ranks among
every such window of the log before it (1 = the largest so far); the vibration's mean and maximum
per axis and the clipping counted in the window. ArduPilot calls vibration under 30 m/s/s
acceptable (PX4's metrics have no such published line: they are shown, not judged); either EKF
gates a velocity innovation only far past these sizes, so a persistent innovation of a few tenths of
a m/s shows in its log without a warning.

ArduPilot's and PX4's innovation is the estimate less the measurement, guard's the measurement less
its estimate: the same inconsistency has opposite signs.

An alarm at which the autopilot's own filter saw the same inconsistency (the same axis and sign,
the largest window of its flight so far) came from the data, not from guard's model of it; whether
the data was attacked, faulty (vibration) or a manoeuvre the autopilot's attitude did not follow is
for the operator, and this is what to look at. guard's own replay gives the alarms and their times
(the log's TimeUS, older logs' TimeMS, or the ULog's timestamp: the same base, once a time that guard
put on the receiver's clock is taken back to the log's: the report's `clock`). A tlog carries no EKF
innovations and is not read.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

INNOVATIONS = ("XKF3", "NKF3", "EKF3")       # EKF3, EKF2, EKF1: IVN, IVE (m/s), core 0
EKF_OF = {"XKF3": "EKF3", "NKF3": "EKF2", "EKF3": "EKF1"}     # the filter each message is of
ACCEPTABLE_VIBE = 30.0                        # m/s/s, ArduPilot's guidance
WINDOW_S = 4.0          # s before each time looked at, by default
SAW_TOP = 3             # the autopilot saw it too: one of its this many largest windows of the flight so far


VIBE_FIELDS = {"dataflash": ("vibration (m/s/s, x y z)", ACCEPTABLE_VIBE),
               "ulog": ("vibration (PX4's accel m/s, gyro rad/s)", None)}


def read_ulog(path: str) -> dict:
    """The same from a PX4 ULog: EKF2's GNSS velocity innovations of its first instance (t s, north,
    east) and the first IMU's vibration metrics (t s, accel, gyro, clipping summed over the axes)."""
    from pyulog import ULog
    log = ULog(path, ["estimator_innovations", "vehicle_imu_status", "ekf2_innovations", "estimator_status"])
    innov, vibe = np.empty((0, 3)), np.empty((0, 4))
    old_innov, old_vibe = innov, vibe           # PX4 before 1.11: read where the newer topics are absent
    for d in log.data_list:
        if d.multi_id != 0:
            continue
        t = d.data["timestamp"] / 1e6
        if d.name == "estimator_innovations" and "gps_hvel[0]" in d.data:
            innov = np.column_stack([t, d.data["gps_hvel[0]"], d.data["gps_hvel[1]"]]).astype(float)
        elif d.name == "vehicle_imu_status" and "accel_vibration_metric" in d.data:
            clip = sum(d.data.get(f"accel_clipping[{i}]", np.zeros_like(t)) for i in range(3))
            vibe = np.column_stack([t, d.data["accel_vibration_metric"], d.data["gyro_vibration_metric"],
                                    clip]).astype(float)
        elif d.name == "ekf2_innovations" and "vel_pos_innov[0]" in d.data:
            old_innov = np.column_stack([t, d.data["vel_pos_innov[0]"], d.data["vel_pos_innov[1]"]]).astype(float)
        elif d.name == "estimator_status" and "vibe[2]" in d.data:
            old_vibe = np.column_stack([t, d.data["vibe[2]"], d.data["vibe[1]"], np.zeros_like(t)]).astype(float)
    innov = innov if len(innov) else old_innov
    vibe = vibe if len(vibe) else old_vibe
    return {"ekf": "EKF2" if len(innov) else None, "innovations": innov, "vibe": vibe, "format": "ulog"}


def read(path: str) -> dict[str, np.ndarray]:
    """The log's EKF velocity innovations (t s, IVN, IVE; core 0 of the EKF the autopilot flew on,
    AHRS_EKF_TYPE, else the first type found) and vibration
    (t s, VibeX, VibeY, VibeZ, clip count summed over the IMUs; the first IMU)."""
    from pymavlink import DFReader
    log = DFReader.DFReader_binary(path, zero_time_base=True)
    innov: dict[str, list] = {t: [] for t in INNOVATIONS}
    vibe: list = []
    while (m := log.recv_match(type=[*INNOVATIONS, "VIBE"])) is not None:
        kind = m.get_type()
        if getattr(m, "C", 0) not in (0, None) or getattr(m, "IMU", 0) not in (0, None):
            continue                               # core 0, the first IMU
        t = m.TimeUS / 1e6 if getattr(m, "TimeUS", None) is not None else m.TimeMS / 1e3    # older logs: ms
        if kind == "VIBE":
            clip = sum(getattr(m, f"Clip{i}", 0) or 0 for i in range(3)) + (getattr(m, "Clip", 0) or 0)
            vibe.append((t, m.VibeX, m.VibeY, m.VibeZ, clip))
        elif hasattr(m, "IVN") and hasattr(m, "IVE"):
            innov[kind].append((t, m.IVN, m.IVE))
    used = {2: "NKF3", 3: "XKF3"}.get(int(log.params.get("AHRS_EKF_TYPE", 0) or 0))   # the EKF it flew on
    kind = used if used and innov[used] else next((k for k in INNOVATIONS if innov[k]), None)
    return {"ekf": EKF_OF.get(kind), "innovations": np.array(innov[kind] if kind else [], dtype=float).reshape(-1, 3),
            "vibe": np.array(vibe, dtype=float).reshape(-1, 5), "format": "dataflash"}


def report_time_as_logged(t_us: int, clock: dict | None) -> int:
    """A time of guard's report back on the log's own clock, where the autopilot's records are: the
    report's times are on the receiver's clock where the autopilot's did not keep time (its `clock`)."""
    from guard.sources.base import as_logged as back
    return back(t_us, (clock["t0_usec"], clock["rate"]) if clock else None)


def read_log(path: str, kind: str) -> dict:
    """`read` or `read_ulog`, by the log's format ("dataflash" or "ulog", as guard's report names it)."""
    return read(path) if kind == "dataflash" else read_ulog(path)


def saw_too(v: dict, alarm: dict) -> bool | None:
    """Whether the autopilot's EKF saw a GNSS velocity alarm's inconsistency too: on the alarm's axis, the
    same way (its innovation's sign the opposite of guard's), one of its SAW_TOP largest windows of the
    flight so far. None where it cannot say: another sensor's alarm, no innovations there, or zeros."""
    key = f"innovation_{alarm['channel']}_mps"
    if alarm["sensor"] != "gnss_vel" or key not in v or v.get("innovation_zero"):
        return None
    return v[key] * alarm["offset"] < 0 and v[f"innovation_{alarm['channel']}_rank"] <= SAW_TOP


def window_means(innov: np.ndarray, window: float) -> np.ndarray:
    """(end time, mean IVN, mean IVE) of every window of `window` s, ends 1 s apart."""
    if len(innov) == 0:
        return np.empty((0, 3))
    ends = np.arange(innov[0, 0] + window, innov[-1, 0] + 1.0, 1.0)
    out = []
    for end in ends:
        s = (innov[:, 0] > end - window) & (innov[:, 0] <= end)
        if s.any():
            out.append((end, *innov[s, 1:].mean(axis=0)))
    return np.array(out).reshape(-1, 3)


def view(data: dict, at: float, window: float) -> dict:
    """The autopilot's view over the `window` s before `at` (s, the log's time)."""
    out: dict = {"at_s": round(at, 2), "window_s": window, "ekf": data["ekf"]}
    innov, vibe = data["innovations"], data["vibe"]
    s = (innov[:, 0] > at - window) & (innov[:, 0] <= at) if len(innov) else np.zeros(0, bool)
    if s.any():
        means = window_means(innov[innov[:, 0] <= at], window)
        for i, axis in ((1, "north"), (2, "east")):
            m = float(innov[s, i].mean())
            earlier = np.abs(means[means[:, 0] <= at, i])
            out[f"innovation_{axis}_mps"] = round(m, 3)
            out[f"innovation_{axis}_rank"] = int((earlier > abs(m) + 1e-9).sum()) + 1
            out[f"innovation_{axis}_windows"] = int(len(earlier)) + 1      # and this one
        out["innovation_zero"] = bool(not innov[s, 1:].any())    # an EKF not fusing GNSS logs zeros
    v = (vibe[:, 0] > at - window) & (vibe[:, 0] <= at) if len(vibe) else np.zeros(0, bool)
    if v.any():
        out["vibe_mean"] = [float(f"{x:.3g}") for x in vibe[v, 1:-1].mean(axis=0)]
        out["vibe_max"] = [float(f"{x:.3g}") for x in vibe[v, 1:-1].max(axis=0)]
        before = vibe[vibe[:, 0] <= at - window, -1]
        out["clipping"] = int(vibe[v, -1].max() - (before[-1] if len(before) else vibe[v, -1].min()))
    out["vibe_is"], limit = VIBE_FIELDS[data.get("format", "dataflash")]
    out["vibe_over_limit"] = bool(limit is not None and "vibe_max" in out and max(out["vibe_max"]) > limit)
    return out


def say(v: dict, alarm: dict | None) -> str:
    head = f"{v['at_s']:.2f} s"
    if alarm:
        names = "|".join([alarm["sensor"], *alarm["ambiguous_with"]])
        head += f": guard's alarm {names} {alarm['channel']} {alarm['offset']:+.2f}"
    lines = [head]
    if alarm and saw_too(v, alarm):
        lines[0] += f" (the autopilot saw it too: one of its {SAW_TOP} largest windows so far, the same way)"
    if "innovation_north_mps" in v:
        lines.append(f"  the autopilot's {v['ekf']} GNSS velocity innovation over the {v['window_s']:g} s before: "
                     f"north {v['innovation_north_mps']:+.2f} m/s (rank {v['innovation_north_rank']} of "
                     f"{v['innovation_north_windows']} windows up to it), east {v['innovation_east_mps']:+.2f} m/s "
                     f"(rank {v['innovation_east_rank']} of {v['innovation_east_windows']})"
                     + ("; every one 0: the autopilot was not fusing the GNSS there" if v["innovation_zero"] else ""))
    else:
        lines.append("  no EKF velocity innovations in the log there (XKF3/NKF3/EKF3, estimator_innovations, "
                     "ekf2_innovations)")
    if "vibe_mean" in v:
        lines.append(f"  {v['vibe_is']}: mean {' '.join(f'{x:g}' for x in v['vibe_mean'])}, "
                     f"max {' '.join(f'{x:g}' for x in v['vibe_max'])}"
                     f"{' (over ArduPilot' + chr(39) + 's 30)' if v['vibe_over_limit'] else ''}; "
                     f"clipping {v['clipping']}")
    else:
        lines.append("  no vibration record in the log there (VIBE, vehicle_imu_status, estimator_status)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("log", help="an ArduPilot DataFlash log (.bin) or a PX4 ULog (.ulg)")
    p.add_argument("--at", type=float, action="append", help="a time of the log in s (repeatable); "
                   "default: each alarm of guard's replay")
    p.add_argument("--window", type=float, default=WINDOW_S, help=f"seconds before each time (default {WINDOW_S:g})")
    p.add_argument("--json", help="write the views as JSON here")
    args = p.parse_args(argv)
    from guard.errors import GuardError
    from guard.sources import log_format
    try:
        kind = log_format(args.log)
    except GuardError as e:
        print(f"autopilot_view: {e}", file=sys.stderr)
        return 2
    if kind not in ("dataflash", "ulog"):
        print(f"autopilot_view: {args.log}: {kind or 'not a log guard reads'}, not DataFlash or ULog: only an "
              "autopilot's own log carries its EKF's innovations", file=sys.stderr)
        return 2
    try:
        data = read_log(args.log, kind)
    except Exception as e:                         # pymavlink and pyulog raise what they raise on a corrupt file
        reader = "pymavlink" if kind == "dataflash" else "pyulog"
        print(f"autopilot_view: {args.log}: {reader} could not read it ({type(e).__name__}: {e})", file=sys.stderr)
        return 2
    alarms: list[dict] = []
    if not args.at:
        from guard.config import Config
        from guard.runtime.replay import replay
        try:
            report = replay(args.log, Config())
        except GuardError as e:
            print(f"autopilot_view: {e}", file=sys.stderr)
            return 2
        alarms = report["alarms"]
        if not alarms:
            print(f"{args.log}: guard raised no alarm; --at T to look at a time")
    times = [(report_time_as_logged(a["time_usec"], report.get("clock")) / 1e6, a) for a in alarms] \
        or [(t, None) for t in args.at or []]
    views = []
    for t, alarm in times:
        v = view(data, t, args.window)
        print(say(v, alarm))
        views.append({**v, "alarm": alarm})
    if args.json:
        Path(args.json).write_text(json.dumps(views, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
