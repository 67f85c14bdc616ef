"""A compass's deviation by heading over a whole log: its hard iron, fitted against the gyro.

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

    chi_m(t) = chi(t) + dev(chi(t), d),   chi(t) = (1 + s) Gamma(t) + k0 + drift(t)

with per stretch k0 (where the heading started) and a drift, continuous, whose slope (the gyro's
bias) is its own in each piece of the stretch of at most PIECE_S (a gyro's bias wanders over
minutes: `drift_basis`), per log s (the gyro's
scale, held near 0 by a prior of GYRO_SCALE: over half a circle a deviation looks like a scale
error), fitted by iteratively reweighted Gauss-Newton (Huber's weights). Per log: d, its standard
error (counting one independent reading per CORR_S: a compass's errors last seconds), the largest
deviation it makes, the compass's scatter about the fit with it and without it (d = 0), and how much
of the circle the headings read cover. A log whose turns do not show the iron (its standard error
over MAX_SIGMA, or its headings over less than MIN_COVER_DEG) says so (`iron_of`); so does one
without a magnetometer or an IMU fast enough to integrate.

`Headings` listens to a replay; `iron_of` fits what it heard. tools/compass_deviation.py runs it over
folders of logs (and fits the motors' field beside it).

`LiveCheck` is the same for `guard run`: it keeps fewer readings (one per LIVE_ROW_S, the latest
LIVE_ROWS of them), fits them every CHECK_S of the samples' time and at the magnetometer's first
alarm, and says its line once (a WARNING on the link and in the log), the first time a fit explains
the compass; once the turns show a compass that reads true (over the readings before the first
alarm, where there was one) it stops and holds nothing. An operator hears in the first minutes of
turning that the compass needs calibrating, rather than reading it off the magnetometer's alarms.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import asdict, dataclass

import numpy as np

from guard.core.aiding.imu import level
from guard.core.aiding.tilt import Tilt
from guard.core.monitor import MonitorConfig
from guard.core.timebase import Timebase
from guard.model.events import Alarm
from guard.runtime.every import Live
from guard.model.samples import Attitude, ImuSample
from guard.model.sensors import Sensor

GAP_S = 0.5             # a stretch ends at a gap in the IMU this long (or a clock that goes back)
MIN_STRETCH_S = 10.0    # shorter stretches are left out
PIECE_S = 60.0          # a longer stretch's drift is fitted in pieces this long at most, each its own gyro bias
ROW_S = 0.05            # one compass reading kept per this long
HUBER = 2.5             # residuals beyond this many robust sigmas weigh less
ITERATIONS = 25         # at most; the fit stops where no parameter moves by CONVERGED
CONVERGED = 1e-7        # rad (or rad/s, or a fraction of the field): far below any figure it gives
MAX_STEP = 0.1          # Gauss-Newton moves the iron at most this far per iteration
CORR_S = 2.0            # one independent reading per this long, in the standard error
MAX_SIGMA = 0.05        # the iron is shown where its standard error is below this (3 degrees)
MIN_FIELD = 0.2         # the field left once the iron is taken away: a fit that needs less has failed
                        # (the simulator's irons, at most 0.5 on each axis, stay within it)
GYRO_SCALE = 0.01       # the gyro's scale error, 1 sigma (a calibrated MEMS gyro's): a prior, not a free
                        # parameter, as over half a circle a deviation looks like a scale error
MIN_COVER_DEG = 180.0   # the headings read must cover this much of the circle for the iron to be shown
MAX_STRETCHES = 30      # the longest stretches fitted, at most (each has its own start and drift)
MAX_ROWS = 40_000       # readings fitted, at most: over half an hour of them
SAY_DEG = 5.0           # a deviation this large guard replay says, where its fit shows it beyond its own
                        # error (its size less twice its standard error) and explains the compass (its
                        # scatter under EXPLAINS of the scatter without it): about three times the
                        # magnetometer's default floor (filter.heading_sigma_rad, 1.7 degrees)
EXPLAINS = 0.7
CHECK_S = 60.0          # guard run fits what it heard this often (the samples' time)
LIVE_ROW_S = 0.2        # ... from one compass reading per this long
LIVE_ROWS = 3000        # ... the latest this many (10 minutes of them): a fit of a few milliseconds
LIVE_STRETCHES = 10     # ... in at most this many stretches (a lossy link's gaps cut many short ones)


class Headings:
    """A replay's listener: each compass reading's heading and the gyro's integral since its stretch began.
    It reads samples only (the monitor need not record its tests for it), and of the IMU's those the
    core's time base (guard.core.timebase) takes, as the monitor does: a frame sent again, one out of
    order and a lone wild stamp are dropped, a reboot's new clock confirmed (its base the IMU's latest
    sample, as the monitor's is before its first fix; after it, the filter's time). `cfg`: the monitor's
    configuration (its min_imu_hz and max_gap_s)."""

    needs_tests = False

    def __init__(self, row_s: float = ROW_S, max_stretches: int = MAX_STRETCHES, cfg: MonitorConfig | None = None):
        cfg = cfg or MonitorConfig()
        self.row_s, self.max_stretches, self.min_imu_hz = row_s, max_stretches, cfg.min_imu_hz
        self.timebase = Timebase(cfg.max_gap_s, Counter())
        self._row_due_us = 0.0              # when the next compass reading is kept
        self.taken = False                  # whether the last sample was an IMU sample taken
        self.tilt = Tilt()
        self.stretches: list[list[tuple[float, float, float]]] = []   # (t s, Gamma, chi_m)
        self._t: int | None = None
        self._gamma = 0.0
        self.intervals: list[int] = []
        self.imu_samples = 0

    def on_sample(self, sample) -> None:
        self.taken = False
        if isinstance(sample, Attitude):
            self.tilt.set(sample)
            return
        if not isinstance(sample, ImuSample):
            return
        verdict = self.timebase.check("imu", sample.t_us, None)     # its base: the IMU's latest taken
        if verdict == "drop":
            return
        if verdict == "rebase":
            self.timebase.reset()
            self.timebase.check("imu", sample.t_us, None)
            self._t = None                  # a new clock: a new stretch
        self.taken = True
        self.imu_samples += 1
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
        if mag is not None and (not rows or sample.t_us >= self._row_due_us):
            rows.append((sample.t_us / 1e6, self._gamma, math.atan2(-mag[1], mag[0])))
            # the next a tenth early: an IMU's period a hair under a divisor of row_s (a 50 Hz IMU's
            # 19,992 us) would otherwise space the readings a whole sample more apart
            self._row_due_us = sample.t_us + 0.9 * self.row_s * 1e6

    def on_events(self, events) -> None:
        pass

    def arrays(self, until_s: float | None = None) -> tuple[np.ndarray, ...] | None:
        """(t from its stretch's start, Gamma, chi_m, stretch number) of the stretches long enough, and
        each reading's time on the samples' clock (s); only the readings before `until_s` (s, on that
        clock) where given. At most `max_stretches` stretches, the longest, and MAX_ROWS readings, every
        k-th where there are more (a long log with many gaps would otherwise make the fit's matrix,
        readings by the stretches and their minutes, too large)."""
        rows = (self.stretches if until_s is None else
                [[x for x in r if x[0] < until_s] for r in self.stretches])
        kept = [np.array(r) for r in rows if len(r) > 20 and r[-1][0] - r[0][0] >= MIN_STRETCH_S]
        if not kept:
            return None
        if len(kept) > self.max_stretches:
            longest = sorted(range(len(kept)), key=lambda j: kept[j][-1, 0] - kept[j][0, 0])[-self.max_stretches:]
            kept = [kept[j] for j in sorted(longest)]
        every = -(-sum(len(a) for a in kept) // MAX_ROWS)
        if every > 1:
            kept = [a[::every] for a in kept]
        return (np.concatenate([a[:, 0] - a[0, 0] for a in kept]), np.concatenate([a[:, 1] for a in kept]),
                np.concatenate([a[:, 2] for a in kept]),
                np.concatenate([np.full(len(a), j) for j, a in enumerate(kept)]),
                np.concatenate([a[:, 0] for a in kept]))


def drift_basis(t: np.ndarray, stretch: np.ndarray, n_s: int) -> np.ndarray:
    """The gyro bias's columns: each stretch cut into pieces of equal length, none longer than PIECE_S,
    each with its own bias, the heading continuous across them. Column j is a piece's hinge, the time
    spent in it so far (0 before it, its length after it), on its stretch's rows: the heading's drift
    is then k1_a t over the first piece, k1_a T_a + k1_b (t - T_a) over the next, and so on. One bias
    over a long stretch took a MEMS gyro's wander over minutes for an iron (7 degrees on ArduPilot's
    SITL rover, whose compass has none, against under 1 in pieces); a free start for each piece would
    also take away what a slow turn tells across them."""
    columns = []
    for j in range(n_s):
        m = stretch == j
        length = float(t[m].max())
        n = max(1, math.ceil(length / PIECE_S))
        for a in range(n):
            start, end = length * a / n, length * (a + 1) / n
            c = np.zeros(len(t))
            c[m] = np.clip(t[m] - start, 0.0, end - start)
            columns.append(c)
    return np.column_stack(columns)


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
    B = drift_basis(t, stretch, n_s)
    n_b = B.shape[1]
    k1, s, d = np.zeros(n_b), 0.0, np.zeros(n_d)
    rows = np.arange(len(t))
    i_s = n_s + n_b                                 # the gyro scale's column; the iron's follow it
    n_p = i_s + 1 + n_d
    for _ in range(ITERATIONS):
        chi = (1.0 + s) * gamma + k0[stretch] + B @ k1
        dx, dy = (0.0, 0.0) if n_d == 0 else (d[0], d[1]) if n_d == 2 else (d[0] + d[2] * u, d[1] + d[3] * u)
        dev, d_chi, d_dx, d_dy = deviations(chi, dx, dy)
        r = wrap(chi_m - chi - dev)
        sigma = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-6)
        w = np.minimum(1.0, HUBER * sigma / np.maximum(np.abs(r), 1e-12))
        g = 1.0 + d_chi
        J = np.zeros((len(t), n_p))
        J[rows, stretch] = g
        J[:, n_s:i_s] = g[:, None] * B
        J[:, i_s] = g * gamma
        if n_d:
            J[:, i_s + 1], J[:, i_s + 2] = d_dx, d_dy
        if n_d == 4:
            J[:, -2], J[:, -1] = d_dx * u, d_dy * u
        N = (J * w[:, None]).T @ J
        rhs = (J * w[:, None]).T @ r
        prior = (sigma / GYRO_SCALE) ** 2          # s ~ N(0, GYRO_SCALE^2), in the residuals' units
        N[i_s, i_s] += prior
        rhs[i_s] -= prior * s
        step = np.linalg.lstsq(N, rhs, rcond=None)[0]
        if n_d:
            step *= min(1.0, MAX_STEP / max(float(np.linalg.norm(step[i_s + 1:])), 1e-12))
            d += step[i_s + 1:]
            field = math.hypot(d[0], d[1]) if n_d == 2 else float(np.max(np.hypot(d[0] + d[2] * u, d[1] + d[3] * u)))
            if field > 1.0 - MIN_FIELD:
                return None
        k0 += step[:n_s]
        k1 += step[n_s:i_s]
        s += step[i_s]
        if float(np.max(np.abs(step))) < CONVERGED:
            break
    seconds = sum(float(np.ptp(t[stretch == j])) for j in range(n_s))
    per_second = len(t) / max(seconds, 1e-6)
    return d, sigma, np.linalg.pinv(N) * sigma ** 2 * max(1.0, per_second * CORR_S)


def iron_of(h: Headings, before_us: int | None = None) -> dict:
    """What a replay's Headings show of the compass's iron, JSON-ready: the Fit's fields, its largest
    deviation and whether the turns show it ("shown"); where nothing was fitted, "shown" False and
    "why" (too little turning) or "error" (nothing to fit). Only the readings before `before_us` (on
    the samples' clock) where given: "before" then says so. `arrays` holds what was fitted (not JSON)."""
    cut = {} if before_us is None else {"before_us": before_us}
    hz = 1e6 / float(np.median(h.intervals)) if h.intervals else 0.0
    if not h.intervals:
        why = (f"its IMU never twice within {GAP_S:g} s, too slow to integrate the gyro" if h.imu_samples
               else "no IMU samples to integrate the gyro")
        return {"shown": False, "error": why, **cut}
    if hz < h.min_imu_hz:
        return {"shown": False, "error": f"its IMU at {hz:.1f} Hz, too slow to integrate the gyro", **cut}
    a = h.arrays(None if before_us is None else before_us / 1e6)
    if a is None:
        return {"shown": False, **cut,
                "error": f"no stretch of compass readings with the IMU of {MIN_STRETCH_S:g} s or more"}
    covered = float(np.unique(np.floor(np.degrees(np.remainder(a[2], 2 * np.pi)) / 10.0)).size * 10.0)
    if covered < MIN_COVER_DEG:
        return {"shown": False, "covered_deg": covered, **cut,
                "why": f"its headings cover {covered:.0f} degrees, too few to show an iron"}
    with_iron, without = fit(*a[:4]), fit(*a[:4], iron=False)
    if with_iron is None or without is None:
        return {"shown": False, "error": "no iron under the field fits its compass", **cut}
    d, scatter, cov = with_iron
    f = Fit(float(d[0]), float(d[1]), float(math.sqrt(max(cov[-2, -2], cov[-1, -1], 0.0))),
            math.degrees(scatter), math.degrees(without[1]), covered)
    return {**asdict(f), "max_deviation_deg": f.max_deviation_deg, "shown": f.shown, **cut, "arrays": a}


def explains(iron: dict) -> bool:
    """Whether a fit shows a deviation of SAY_DEG or more beyond its own error (its size less twice its
    standard error) that explains the compass's readings (their scatter under EXPLAINS of it without)."""
    return (bool(iron.get("shown")) and iron["max_deviation_deg"] >= SAY_DEG
            and math.hypot(iron["dx"], iron["dy"]) - 2.0 * iron["sigma"] >= math.sin(math.radians(SAY_DEG))
            and iron["scatter_deg"] <= EXPLAINS * iron["scatter_without_deg"])


def chosen(whole: dict, before: dict | None) -> dict | None:
    """The fit a line is said of: the one before the magnetometer's first alarm where it explains the
    compass, else the whole one where it does, else None."""
    return before if before is not None and explains(before) else whole if explains(whole) else None


def said(whole: dict, before: dict | None = None, first_alarm_s: float | None = None) -> str | None:
    """guard replay's line on the compass's iron: `whole` fitted over the whole log, `before` over the
    readings before the magnetometer's first alarm (at `first_alarm_s`, the log's time), where it
    had one. A field that came in flight (an attack on the compass, a part come loose) fits as an iron
    too: the line blames the compass's calibration only where the readings before its first alarm show
    the iron; where they turned too little to show it, it says both and when the first alarm came."""
    fit_ = chosen(whole, before)
    if fit_ is None:
        return None
    size = (f"up to {fit_['max_deviation_deg']:.0f} degrees off depending on the heading (a field fixed to the body, "
            f"fitted against the gyro over {fit_['covered_deg']:.0f} degrees of turns: {fit_['scatter_deg']:.1f} "
            f"degrees of scatter with it, {fit_['scatter_without_deg']:.1f} without)")
    cause = "its calibration or its place, which guard's one compass offset cannot hold"
    if fit_ is before:
        return f"the compass read {size} before its first alarm: {cause}"
    if first_alarm_s is None:
        return f"the compass read {size} over the whole log: {cause}"
    return (f"the compass read {size} over the whole log: {cause}, if it was so from the start; a field that came "
            f"in flight (an attack on the compass, a part come loose) fits alike, and the magnetometer's first "
            f"alarm came at {first_alarm_s:.1f} s of the log's time, before the compass had turned enough to show "
            "which")


def compass_fits(h: Headings, report: dict) -> tuple[dict, dict | None, float | None]:
    """A replay's fits, JSON-ready: over the whole log, over the readings before the magnetometer's
    first alarm (None without one), and that alarm's time (s, as the report's times)."""
    first = min((a["time_usec"] for a in report["alarms"] if a["sensor"] == "mag"), default=None)
    whole = iron_of(h)
    whole.pop("arrays", None)
    if first is None:
        return whole, None, None
    before = iron_of(h, first)
    before.pop("arrays", None)
    return whole, before, first / 1e6


class LiveCheck(Live, Headings):
    """guard run's compass check (a sink): `say(line)` once, where a fit explains the compass.

    At the magnetometer's first alarm it fits the readings before it; every CHECK_S it fits all it
    holds. The line is `said`'s, shorter for a ground station (a STATUSTEXT holds 50 bytes): the
    calibration is blamed alone only where the readings before the first alarm show the iron. Once it
    has said its line, or the turns show a compass that reads true, it stops listening."""

    def __init__(self, say, cfg: MonitorConfig | None = None):
        super().__init__(LIVE_ROW_S, LIVE_STRETCHES, cfg)
        self.live(say, CHECK_S)
        self.before: dict | None = None             # the fit before the magnetometer's first alarm
        self.first_alarm: int | None = None         # ... and its GNSS sample k

    def ticks(self, sample) -> bool:
        return self.taken

    def on_events(self, events) -> None:
        if self.done or self.first_alarm is not None:
            return
        alarm = next((e for e in events if isinstance(e, Alarm) and e.sensor == Sensor.MAG), None)
        if alarm is None:
            return
        self.first_alarm = alarm.gnss_index
        self.before = iron_of(self, alarm.t_us)
        self.before.pop("arrays", None)
        if explains(self.before):
            self._say(self.before, alarm.t_us)
        elif self.before.get("shown"):      # the turns before it showed a compass that read true: what
            self.stop()                     # came after is no calibration's

    def check(self, t_us: int) -> None:
        """Fit what it holds (the latest LIVE_ROWS readings) at t_us; say the line, or stop where the
        turns show a compass that reads true."""
        self._trim()
        whole = iron_of(self)
        whole.pop("arrays", None)
        fit_ = chosen(whole, self.before)
        if fit_ is not None:
            self._say(fit_, t_us)
        elif whole.get("shown"):           # turned enough to show an iron, and none explains the compass
            self.stop()

    def _say(self, fit_: dict, t_us: int) -> None:
        line = (f"compass reads up to {fit_['max_deviation_deg']:.0f} deg off by heading (fitted on "
                f"{fit_['covered_deg']:.0f} deg of turns): calibrate it, or move it from the wiring")
        if fit_ is not self.before and self.first_alarm is not None:
            line += (f"; or a field came in flight (an attack fits alike): its first alarm, k={self.first_alarm}, "
                     "came before the turns could tell")
        self.tell(t_us, line)

    def let_go(self) -> None:
        self.stretches, self.intervals = [], []

    def _trim(self) -> None:
        extra = sum(len(r) for r in self.stretches) - LIVE_ROWS
        while extra > 0 and self.stretches:
            first = self.stretches[0]
            if len(first) <= extra and len(self.stretches) > 1:
                extra -= len(first)
                self.stretches.pop(0)
            else:
                del first[:extra]
                extra = 0
