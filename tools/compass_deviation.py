"""How far a vehicle's compass is off by heading: its hard iron, fitted to each log against the gyro
(guard.runtime.deviation: the model and the fit), and the motors' field beside it.

    python tools/compass_deviation.py FOLDER_OR_LOG [...] [--jobs 2] [--json out.json]

Per log: the iron d, its standard error, the largest deviation it makes, the compass's scatter
about the fit with it and without it, and how much of the circle the headings read cover; a log whose
turns do not show it says so; a log without a magnetometer, an IMU fast enough to integrate, or one
that cannot be read, is named and skipped.

Where the iron is shown, the log is replayed again with it taken out of every magnetometer reading
from the first (`iron_out`: each reading turned about the vertical by the deviation the iron makes
at its heading), and its new alarms by sensor are shown both ways: what learning the iron could buy
at most, as no filter could know it before the turns showed it.

The motors' field. The motors' and the battery's current is a field in the body too, and it grows
with the current: ArduPilot's compassmot calibration measures it per ampere or per unit of throttle.
Where the log says a multicopter's throttle u (0 to 1: ArduCopter's CTUN.ThO, older logs' ThrOut
/ 1000; PX4's multicopter thrust, vehicle_thrust_setpoint or actuator_controls_0, while
vehicle_status says rotary wing; not a plane's, whose throttle is its forward motor's, nor a tlog's,
whose VFR_HUD has no time of the autopilot's), the fit is made again with the body's field

    d(t) = d_0 + m (u(t) - u_med)

m = (m_x, m_y) the motors' field per unit of throttle, d_0 the body's field at the flight's median
throttle u_med (measured from it, so that d_0 and m are not one another's), fitted over the
readings with the motors running (u over MIN_THROTTLE), and shown beside the iron's: the scatter
with d_0 alone and with d_0 and m over the same readings, and the most by which m turns the heading,
over every heading, between the two ends of the throttle's usual spread (its 5th to 95th percentile;
shown where m's standard error times that spread is under MAX_SIGMA). Where a compassmot
calibration would take out much of the compass's error in flight, the two scatters differ by much.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from guard.errors import GuardError                  # noqa: E402
from guard.core.aiding.tilt import Tilt             # noqa: E402
from guard.model.samples import Attitude, ImuSample  # noqa: E402
from guard.runtime.deviation import MAX_SIGMA, Headings, deviations, fit, iron_of, wrap   # noqa: E402
from guard.runtime.replay import replay              # noqa: E402
from guard.sources.dataflash.index import MAX_BOOT_US, Log, looks_like_dataflash, open_index   # noqa: E402
from guard.sources.dataflash.survey import FIRMWARE   # noqa: E402
from guard.sources.ulog.load import load, looks_like_ulog   # noqa: E402
from real_logs import each_log                       # noqa: E402 (beside this file)

MIN_THROTTLE = 0.05     # the motors run (a throttle under this: idle or stopped)
MIN_THROTTLE_SPREAD = 0.05   # the throttle's spread (its 95th percentile less its 5th) that can show m
VEHICLE_TYPE_ROTARY_WING = 1    # PX4's vehicle_status.vehicle_type of a multicopter (or a VTOL hovering)
BUILD_COPTER = {2: "copter"}    # ArduPilot's VER.BU of a multicopter (APM_BUILD_ArduCopter)


def throttle_of(path: str) -> tuple[np.ndarray | None, str]:
    """A multicopter's throttle (rows of t s on the log's own clock, u from 0 to 1), or None and why not."""
    with open(path, "rb") as f:
        head = f.read(16)
    if looks_like_ulog(head):
        return _ulog_throttle(path)
    if looks_like_dataflash(head):
        return _dataflash_throttle(path)
    return None, "a tlog's throttle (VFR_HUD) has no time of the autopilot's: not read"


def _dataflash_throttle(path: str) -> tuple[np.ndarray | None, str]:
    log = Log(open_index(path))
    kind = next((m.group(1).lower() for _, text in log.texts("MSG", "Message") if (m := FIRMWARE.match(text))), None)
    if kind is None and log.format("VER") is not None and "BU" in log.format("VER").colhash:
        kind = next((BUILD_COPTER.get(build, f"build {build}") for _, build in log.rows("VER", ["BU"])), None)
    if kind != "copter":
        return None, f"its throttle is not a multicopter's lift (the log says {kind or 'no vehicle'})"
    fmt = log.format("CTUN")
    column = next((c for c in ("ThO", "ThrOut") if fmt is not None and c in fmt.colhash), None)
    if column is None:
        return None, "no throttle in this log (CTUN.ThO or ThrOut)"
    scale = 1.0 if column == "ThO" else 1e-3                # older logs: per mille
    rows = [(t / 1e6, u * scale) for t, u in log.rows("CTUN", [column])
            if 0 <= t < MAX_BOOT_US and u is not None and math.isfinite(u)]
    return (np.array(rows, dtype=float), "") if rows else (None, "no throttle in this log (CTUN without time)")


def _ulog_throttle(path: str) -> tuple[np.ndarray | None, str]:
    ulog, _, _ = load(path, ["vehicle_thrust_setpoint", "actuator_controls_0", "vehicle_status"])
    found = {d.name: d.data for d in ulog.data_list if d.multi_id == 0}
    if "vehicle_thrust_setpoint" in found and "xyz[2]" in found["vehicle_thrust_setpoint"]:
        d = found["vehicle_thrust_setpoint"]
        u = -d["xyz[2]"]                            # up is -z (FRD)
    elif "actuator_controls_0" in found and "control[3]" in found["actuator_controls_0"]:
        d = found["actuator_controls_0"]
        u = d["control[3]"]
    else:
        return None, "no throttle in this log (vehicle_thrust_setpoint, actuator_controls_0)"
    t = d["timestamp"] / 1e6
    status = found.get("vehicle_status", {})
    if "vehicle_type" in status:                    # a multicopter's thrust only while it flies as one
        ts = status["timestamp"] / 1e6
        latest = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 1)
        rotary = status["vehicle_type"][latest] == VEHICLE_TYPE_ROTARY_WING
        t, u = t[rotary], u[rotary]
    if not len(t):
        return None, "its throttle is not a multicopter's lift (it never flies as one)"
    return np.column_stack([t, u]).astype(float), ""


def on_samples_clock(t_log_s: np.ndarray, clock: dict | None) -> np.ndarray:
    """Times of the log's own clock (s) on the samples' (the report's `clock`, where guard put the log
    on its receiver's time: guard.sources.base.as_logged the other way)."""
    if not clock:
        return t_log_s
    t0 = clock["t0_usec"] / 1e6
    return t0 + (t_log_s - t0) * clock["rate"]


def motors(a: tuple[np.ndarray, ...], throttle: np.ndarray, clock: dict | None) -> dict:
    """The motors' field fitted over the readings with the motors running (see the module's doc), or
    why not ("why")."""
    if len(throttle) < 2:
        return {"why": "no throttle in this log"}
    t_thr = on_samples_clock(throttle[:, 0], clock)
    order = np.argsort(t_thr)
    u = np.interp(a[4], t_thr[order], throttle[order, 1], left=np.nan, right=np.nan)
    running = np.isfinite(u) & (u > MIN_THROTTLE)
    if running.sum() < 50:
        return {"why": "the motors barely run under the compass's readings"}
    u = np.clip(u[running], 0.0, 1.0)
    u_med, spread = float(np.median(u)), float(np.percentile(u, 95) - np.percentile(u, 5))
    if spread < MIN_THROTTLE_SPREAD:
        return {"why": f"the throttle barely moves ({spread:.2f}): too little to show the motors' field"}
    t, gamma, chi_m, stretch = (x[running] for x in a[:4])
    _, stretch = np.unique(stretch, return_inverse=True)
    iron_only, with_motors = fit(t, gamma, chi_m, stretch), fit(t, gamma, chi_m, stretch, u=u - u_med)
    if iron_only is None or with_motors is None:
        return {"why": "no field under the earth's fits its compass with the motors running"}
    d, scatter, cov = with_motors
    sigma = float(math.sqrt(max(cov[-2, -2], cov[-1, -1], 0.0)))
    return {"mx": float(d[2]), "my": float(d[3]), "sigma": sigma, "shown": sigma * spread < MAX_SIGMA,
            "scatter_deg": math.degrees(scatter), "scatter_iron_only_deg": math.degrees(iron_only[1]),
            "throttle_median": u_med, "throttle_spread": spread, "over_spread_deg": turned_by(d, spread)}


def turned_by(d: np.ndarray, spread: float) -> float:
    """The most (degrees, over every heading) by which the motors' field m turns the heading between
    the throttle half its spread below the median and half above: the field's deviation computed at
    both, the iron d_0 with it (a field weakened by the iron turns further)."""
    chi = np.linspace(-np.pi, np.pi, 721)
    lo = deviations(chi, d[0] - d[2] * spread / 2, d[1] - d[3] * spread / 2)[0]
    hi = deviations(chi, d[0] + d[2] * spread / 2, d[1] + d[3] * spread / 2)[0]
    return math.degrees(float(np.max(np.abs(wrap(hi - lo)))))


def iron_out(dx: float, dy: float):
    """An `inject` for replay: each magnetometer reading turned about the vertical by the deviation
    the iron d makes at its heading, so that guard levels it to what it would read without the iron
    (the heading read chi_m back to chi: chi_m = atan2(sin chi - d_y, cos chi + d_x), solved for chi
    along the ray chi_m). It is levelled with the autopilot's attitude, as guard levels it
    (guard.core.aiding.imu.level), and turned back to the body: its vertical part is untouched."""
    def inject(samples):
        tilt = Tilt()
        for s in samples:
            if isinstance(s, Attitude):
                tilt.set(s)
            elif isinstance(s, ImuSample) and s.mag_x_gauss is not None:
                phi, p = tilt.at(s)
                cr, sr, cp, sp = math.cos(phi), math.sin(phi), math.cos(p), math.sin(p)
                L = np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])
                m = L @ np.array([s.mag_x_gauss, s.mag_y_gauss, s.mag_z_gauss])
                chi_m = math.atan2(-m[1], m[0])
                ux, uy = math.cos(chi_m), math.sin(chi_m)
                along = ux * dx - uy * dy
                reach = along + math.sqrt(max(along * along - dx * dx - dy * dy + 1.0, 0.0))
                turn = math.atan2(reach * uy + dy, reach * ux - dx) - chi_m
                c, n = math.cos(turn), math.sin(turn)
                m[0], m[1] = c * m[0] + n * m[1], -n * m[0] + c * m[1]
                b = L.T @ m
                s = dataclasses.replace(s, mag_x_gauss=float(b[0]), mag_y_gauss=float(b[1]), mag_z_gauss=float(b[2]))
            yield s
    return inject


def alarms_by_sensor(report: dict) -> dict[str, int]:
    """A report's new alarms (not a standing one going on) by sensor."""
    return dict(Counter(a["sensor"] for a in report.get("alarms", []) if not a.get("standing")))


def deviation_of(path: str) -> dict:
    """One log's fit, as a JSON-ready dict (an "error" where it has none)."""
    h = Headings()
    try:
        report = replay(path, listeners=[h])
    except GuardError as e:
        return {"log": path, "error": str(e)}
    except Exception as e:                  # noqa: BLE001 - one unreadable log is named, the others still run
        return {"log": path, "error": f"{type(e).__name__}: {e}"}
    iron = iron_of(h)
    a = iron.pop("arrays", None)
    if a is None:
        return {"log": path, **iron}
    try:
        throttle, why = throttle_of(path)
    except GuardError as e:                 # the iron is still shown
        throttle, why = None, f"its throttle could not be read: {e}"
    mot = motors(a, throttle, report.get("clock")) if throttle is not None else {"why": why}
    # what learning the iron could buy at most: the same log with the whole log's iron out of every
    # reading from its first (a filter that learnt it would know it only after the turns showed it)
    out = alarms_by_sensor(replay(path, inject=iron_out(iron["dx"], iron["dy"]))) if iron["shown"] else None
    return {"log": path, **iron, "motors": mot, "alarms": alarms_by_sensor(report), "alarms_iron_out": out}


def show(r: dict) -> None:
    name = Path(r["log"]).name
    if "error" in r:
        print(f"{name}: skipped: {r['error']}")
        return
    if "why" in r:
        print(f"{name}: not shown: {r['why']}")
        return
    what = (f"up to {r['max_deviation_deg']:.0f} degrees by heading" if r["shown"]
            else "not shown by its turns")
    print(f"{name}: {what}: hard iron {r['dx']:+.3f} forward, {r['dy']:+.3f} right of the "
          f"horizontal field (+-{r['sigma']:.3f}); the compass against the gyro "
          f"{r['scatter_deg']:.1f} degrees with it, {r['scatter_without_deg']:.1f} without; "
          f"headings over {r['covered_deg']:.0f} degrees")
    if r.get("alarms_iron_out") is not None:
        print(f"  with that iron out of its readings from the first: alarms {said_alarms(r['alarms'])} -> "
              f"{said_alarms(r['alarms_iron_out'])}")
    m = r["motors"]
    if "why" in m:
        print(f"  the motors' field: not fitted: {m['why']}")
        return
    shown = m["shown"]
    print(f"  the motors' field: {m['mx']:+.3f} forward, {m['my']:+.3f} right per unit of throttle "
          f"(+-{m['sigma']:.3f}{'' if shown else ', not shown'}), turning the heading by up to "
          f"{m['over_spread_deg']:.1f} degrees over the throttle's usual spread ({m['throttle_spread']:.2f} about "
          f"{m['throttle_median']:.2f}); with the motors running the compass against the gyro "
          f"{m['scatter_deg']:.1f} degrees with it, {m['scatter_iron_only_deg']:.1f} with the iron alone")


def said_alarms(by_sensor: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(by_sensor.items())) or "none"


def main(argv=None) -> int:
    results = each_log(__doc__, deviation_of, show, argv)
    if isinstance(results, int):
        return results
    shown = [r for r in results if r.get("shown")]
    if shown:
        devs = sorted(r["max_deviation_deg"] for r in shown)
        print(f"{len(results)} logs: the iron shown in {len(shown)}, its deviation {devs[0]:.0f} to "
              f"{devs[-1]:.0f} degrees")
        before, after = Counter(), Counter()
        for r in shown:
            before.update(r["alarms"])
            after.update(r["alarms_iron_out"])
        print(f"  their new alarms {said_alarms(before)}; with each log's iron out of its readings from the "
              f"first {said_alarms(after)}")
    else:
        print(f"{len(results)} logs: the iron shown in none")
    return 0


if __name__ == "__main__":
    sys.exit(main())
