"""How far a vehicle's compass is off by heading: its hard iron, fitted to each log against the gyro.

    python tools/compass_deviation.py FOLDER_OR_LOG [...] [--jobs 2] [--json out.json]

A field fixed to the body (a calibration's leftover, a battery's wiring, a compass mounted a few
degrees off level where the field is steep) adds to the earth's, and the compass's heading is then
off by an amount that depends on the heading, its deviation:

    chi_m = atan2(sin chi - d_y, cos chi + d_x)

chi the heading clockwise from magnetic north, d = (d_x, d_y) the body's field forward and right as
a fraction of the earth's horizontal one (B sin chi + C cos chi to first order, a ship's deviation
curve). guard's filter learns one constant offset of the compass (b_psi): this is what it cannot.

The fit compares the compass with the gyro, the only other witness of the heading's turns. Along
each stretch of the log without a gap, the gyro's yaw rate, levelled with the autopilot's attitude
as guard levels it, integrates to Gamma(t), and

    chi_m(t) = chi(t) + dev(chi(t), d),   chi(t) = (1 + s) Gamma(t) + k0 + k1 t

with per stretch k0 (where the heading started) and k1 (the gyro's bias), per log s (the gyro's
scale, held near 0 by a prior of GYRO_SCALE: over half a circle a deviation looks like a scale
error), fitted by iteratively reweighted Gauss-Newton (Huber's weights). Per log: d, its standard
error (counting one independent reading per CORR_S: a compass's errors last seconds), the largest
deviation it makes, the compass's scatter about the fit with it and without it (d = 0), and how much
of the circle the headings read cover. A log whose turns do not show the iron (its standard error
over MAX_SIGMA, or its headings over less than MIN_COVER_DEG) says so. A log without a magnetometer,
an IMU fast enough to integrate, or one that cannot be read, is named and skipped.

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

import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from guard.core.aiding.imu import level              # noqa: E402
from guard.sources.dataflash.index import MAX_BOOT_US, Log, looks_like_dataflash, open_index   # noqa: E402
from guard.sources.dataflash.survey import FIRMWARE   # noqa: E402
from guard.sources.ulog.load import load, looks_like_ulog   # noqa: E402
from guard.core.aiding.tilt import Tilt              # noqa: E402
from guard.errors import GuardError                  # noqa: E402
from guard.model.samples import Attitude, ImuSample  # noqa: E402
from guard.runtime.replay import replay              # noqa: E402
from real_logs import each_log                       # noqa: E402 (beside this file)

GAP_S = 0.5             # a stretch ends at a gap in the IMU this long (or a clock that goes back)
MIN_STRETCH_S = 10.0    # shorter stretches are left out
ROW_S = 0.05            # one compass reading kept per this long
HUBER = 2.5             # residuals beyond this many robust sigmas weigh less
ITERATIONS = 25
MAX_STEP = 0.1          # Gauss-Newton moves the iron at most this far per iteration
CORR_S = 2.0            # one independent reading per this long, in the standard error
MAX_SIGMA = 0.05        # the iron is shown where its standard error is below this (3 degrees)
MIN_FIELD = 0.2         # the field left once the iron is taken away: a fit that needs less has failed
                        # (the simulator's irons, at most 0.5 on each axis, stay within it)
GYRO_SCALE = 0.01       # the gyro's scale error, 1 sigma (a calibrated MEMS gyro's): a prior, not a free
                        # parameter, as over half a circle a deviation looks like a scale error
MIN_COVER_DEG = 180.0   # the headings read must cover this much of the circle for the iron to be shown
MIN_IMU_HZ = 8.0        # a slower IMU (telemetry) is not integrated, as guard does not (monitor.min_imu_hz)
MIN_THROTTLE = 0.05     # the motors run (a throttle under this: idle or stopped)
MIN_THROTTLE_SPREAD = 0.05   # the throttle's spread (its 95th percentile less its 5th) that can show m
VEHICLE_TYPE_ROTARY_WING = 1    # PX4's vehicle_status.vehicle_type of a multicopter (or a VTOL hovering)
BUILD_COPTER = {2: "copter"}    # ArduPilot's VER.BU of a multicopter (APM_BUILD_ArduCopter)


class Headings:
    """A replay's listener: each compass reading's heading and the gyro's integral since its stretch began."""

    def __init__(self):
        self.tilt = Tilt()
        self.stretches: list[list[tuple[float, float, float]]] = []   # (t s, Gamma, chi_m)
        self._t: int | None = None
        self._gamma = 0.0
        self.intervals: list[int] = []

    def on_sample(self, sample) -> None:
        if isinstance(sample, Attitude):
            self.tilt.set(sample)
            return
        if not isinstance(sample, ImuSample):
            return
        _, _, rate, mag, _, _ = level(sample, *self.tilt.at(sample))
        if self._t is None or not 0 < sample.t_us - self._t <= GAP_S * 1e6:
            self.stretches.append([])
            self._gamma = 0.0
        else:
            self._gamma -= rate * (sample.t_us - self._t) / 1e6   # rate is ENU: the compass turns clockwise
            if len(self.intervals) < 10_000:
                self.intervals.append(sample.t_us - self._t)
        self._t = sample.t_us
        rows = self.stretches[-1]
        if mag is not None and (not rows or sample.t_us / 1e6 - rows[-1][0] >= ROW_S):
            rows.append((sample.t_us / 1e6, self._gamma, math.atan2(-mag[1], mag[0])))

    def on_events(self, events) -> None:
        pass

    def arrays(self) -> tuple[np.ndarray, ...] | None:
        """(t from its stretch's start, Gamma, chi_m, stretch number) of the stretches long enough, and
        each reading's time on the samples' clock (s)."""
        kept = [np.array(r) for r in self.stretches if len(r) > 20 and r[-1][0] - r[0][0] >= MIN_STRETCH_S]
        if not kept:
            return None
        return (np.concatenate([a[:, 0] - a[0, 0] for a in kept]), np.concatenate([a[:, 1] for a in kept]),
                np.concatenate([a[:, 2] for a in kept]),
                np.concatenate([np.full(len(a), j) for j, a in enumerate(kept)]),
                np.concatenate([a[:, 0] for a in kept]))


def deviations(chi: np.ndarray, dx: float, dy: float):
    """dev(chi, d) = chi_m - chi over arrays, and its derivatives by chi, d_x and d_y."""
    c, s = np.cos(chi), np.sin(chi)
    a, b = c + dx, s - dy
    n2 = np.maximum(a * a + b * b, MIN_FIELD ** 2)
    return wrap(np.arctan2(b, a) - chi), (a * c + b * s) / n2 - 1.0, -b / n2, -a / n2


def wrap(a):
    return np.remainder(a + np.pi, 2 * np.pi) - np.pi


@dataclass(frozen=True)
class Fit:
    dx: float
    dy: float
    sigma: float            # the larger standard error of d_x and d_y
    scatter_deg: float      # the compass's robust scatter about the fit
    scatter_without_deg: float   # ... and about the same fit with d held at 0
    covered_deg: float      # the headings read, in 10 degree bins

    @property
    def max_deviation_deg(self) -> float:
        return math.degrees(math.asin(min(math.hypot(self.dx, self.dy), 1.0)))

    @property
    def shown(self) -> bool:
        return self.sigma < MAX_SIGMA


def fit(t, gamma, chi_m, stretch, iron: bool = True,
        u: np.ndarray | None = None) -> tuple[np.ndarray, float, np.ndarray] | None:
    """(d, the robust scatter, the covariance of the parameters) of the model above; iron False holds
    d at 0; with the throttle u (one per reading), d is (d_0, m), the body's field d_0 + m u. None
    where Gauss-Newton needs an iron as large as the field."""
    n_s = int(stretch.max()) + 1
    k0 = np.array([math.atan2(np.sin(chi_m[stretch == j] - gamma[stretch == j]).mean(),
                              np.cos(chi_m[stretch == j] - gamma[stretch == j]).mean()) for j in range(n_s)])
    n_d = 0 if not iron else 2 if u is None else 4
    k1, s, d = np.zeros(n_s), 0.0, np.zeros(n_d)
    rows = np.arange(len(t))
    n_p = 2 * n_s + 1 + n_d
    for _ in range(ITERATIONS):
        chi = (1.0 + s) * gamma + k0[stretch] + k1[stretch] * t
        dx, dy = (0.0, 0.0) if n_d == 0 else (d[0], d[1]) if n_d == 2 else (d[0] + d[2] * u, d[1] + d[3] * u)
        dev, d_chi, d_dx, d_dy = deviations(chi, dx, dy)
        r = wrap(chi_m - chi - dev)
        sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-6)
        w = np.minimum(1.0, HUBER * sigma / np.maximum(np.abs(r), 1e-12))
        g = 1.0 + d_chi
        J = np.zeros((len(t), n_p))
        J[rows, stretch] = g
        J[rows, n_s + stretch] = g * t
        J[:, 2 * n_s] = g * gamma
        if n_d:
            J[:, 2 * n_s + 1], J[:, 2 * n_s + 2] = d_dx, d_dy
        if n_d == 4:
            J[:, -2], J[:, -1] = d_dx * u, d_dy * u
        N = (J * w[:, None]).T @ J
        rhs = (J * w[:, None]).T @ r
        prior = (sigma / GYRO_SCALE) ** 2          # s ~ N(0, GYRO_SCALE^2), in the residuals' units
        N[2 * n_s, 2 * n_s] += prior
        rhs[2 * n_s] -= prior * s
        step = np.linalg.lstsq(N, rhs, rcond=None)[0]
        if n_d:
            step *= min(1.0, MAX_STEP / max(float(np.linalg.norm(step[2 * n_s + 1:])), 1e-12))
            d += step[2 * n_s + 1:]
            field = math.hypot(d[0], d[1]) if n_d == 2 else float(np.max(np.hypot(d[0] + d[2] * u, d[1] + d[3] * u)))
            if field > 1.0 - MIN_FIELD:
                return None
        k0 += step[:n_s]
        k1 += step[n_s:2 * n_s]
        s += step[2 * n_s]
    seconds = sum(float(np.ptp(t[stretch == j])) for j in range(n_s))
    per_second = len(t) / max(seconds, 1e-6)
    return d, sigma, np.linalg.pinv(N) * sigma ** 2 * max(1.0, per_second * CORR_S)


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
    ulog, _ = load(path, ["vehicle_thrust_setpoint", "actuator_controls_0", "vehicle_status"])
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


def deviation_of(path: str) -> dict:
    """One log's fit, as a JSON-ready dict (an "error" where it has none)."""
    h = Headings()
    try:
        report = replay(path, listeners=[h])
    except GuardError as e:
        return {"log": path, "error": str(e)}
    except Exception as e:                  # noqa: BLE001 - one unreadable log is named, the others still run
        return {"log": path, "error": f"{type(e).__name__}: {e}"}
    hz = 1e6 / float(np.median(h.intervals)) if h.intervals else 0.0
    if hz < MIN_IMU_HZ:
        return {"log": path, "error": f"its IMU at {hz:.1f} Hz, too slow to integrate the gyro"}
    a = h.arrays()
    if a is None:
        return {"log": path, "error": "no stretch of compass readings with the IMU of "
                                      f"{MIN_STRETCH_S:g} s or more"}
    covered = np.unique(np.floor(np.degrees(np.remainder(a[2], 2 * np.pi)) / 10.0)).size * 10.0
    if covered < MIN_COVER_DEG:
        return {"log": path, "shown": False, "covered_deg": covered,
                "why": f"its headings cover {covered:.0f} degrees, too few to show an iron"}
    with_iron, without = fit(*a[:4]), fit(*a[:4], iron=False)
    if with_iron is None or without is None:
        return {"log": path, "error": "no iron under the field fits its compass"}
    d, scatter, cov = with_iron
    f = Fit(float(d[0]), float(d[1]), float(math.sqrt(max(cov[-2, -2], cov[-1, -1], 0.0))),
            math.degrees(scatter), math.degrees(without[1]), covered)
    try:
        throttle, why = throttle_of(path)
    except GuardError as e:                 # the iron is still shown
        throttle, why = None, f"its throttle could not be read: {e}"
    mot = motors(a, throttle, report.get("clock")) if throttle is not None else {"why": why}
    return {"log": path, **asdict(f), "max_deviation_deg": f.max_deviation_deg, "shown": f.shown, "motors": mot}


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


def main(argv=None) -> int:
    results = each_log(__doc__, deviation_of, show, argv)
    if isinstance(results, int):
        return results
    shown = [r for r in results if r.get("shown")]
    if shown:
        devs = sorted(r["max_deviation_deg"] for r in shown)
        print(f"{len(results)} logs: the iron shown in {len(shown)}, its deviation {devs[0]:.0f} to "
              f"{devs[-1]:.0f} degrees")
    else:
        print(f"{len(results)} logs: the iron shown in none")
    return 0


if __name__ == "__main__":
    sys.exit(main())
