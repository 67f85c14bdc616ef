"""How far a receiver's positions wander against its own velocity, and what guard's model allows.

A receiver's position and velocity come from different measurements (code ranges and Doppler): over
T seconds, its position's change less the integral of its velocity is the slow part of its position
error, which no IMU is needed to see. `PositionWander` (a sink of samples) keeps the fixes guard reads
and measures its structure function per axis,

    D(T) = sqrt(E[d^2] / 2),  d = (p(t+T) - p(t)) - integral of v from t to t+T,

against what guard's model of each fix allows for it: its white noise sigma plus the position's random
walk q_pos_m (both as guard.core.aiding.gnss reads the fix, its reported accuracy taken up to what the
receiver usually reports, as the monitor takes it, though over every fix where the monitor hears only
calm ones), D(T)^2 = sigma^2 + q^2 T / 2. The
position's small-shift test (k = 0.5, about BLOCK fixes: 8 s at 5 Hz) sums what wanders on that time
scale, so the ratio at SAY_LAG_S is the one `guard replay` says, and past SAY_RATIO it says what it
means: the receiver's own wander is what its position alarms may be, and guard tune fits it; or, past
the model with the largest random walk guard tune fits (`tunable`: Q_POS_MAX times the default, the
bound of tune's position_walk), that no walk of a receiver's own slow error covers it: a fault or a
spoof, glitches or jumps of tens of metres (on the 70 public logs of the README, the Erle copter's
genuine GPS glitches and the METU car's receiver, which jumps 57 m, and no other). guard tune would
still take such a log, putting what the walk cannot hold into the position's noise floor: a blunter
test, which the line warns against. The bound has no margin: a receiver near it (the METU car reads 1.16
times it) may read either side of it from one flight, or one live check, to the next. On the 47 public
flights of the README, 6 of the 9 past 1.5 raised a position alarm (13 of the 21) and 3 of the other 38
did (8); on 23 public logs that no figure of guard was set on, 2 of 3 (11 alarms) and none of 20
(`python tools/receiver_wander.py FOLDERS` beside `python tools/real_logs.py FOLDERS`). Its growth from
10 to 80 s tells the kind of error: an exponent of 0.5 is a random walk (the model's), 1 a drift held
for tens of seconds, 0 a bounded one.

Fixes without a velocity are left out, and no velocity is integrated across a gap over MAX_GAP_S or a
clock gone back (a reboot starts a new stretch). Each fix's step from the one before is taken in the
plane tangent at that one, where the receiver's velocity is: one plane for a whole flight turns its far
end by its distance over the earth's radius (0.5 mrad at 3 km), which over 10 s at 20 m/s is 10 cm. `PositionWander` keeps the fixes of the whole log (8
numbers a fix: 2.3 MB an hour at 10 Hz). `guard run` says it too, once (`LivePositionWander`): every
LIVE_CHECK_S of the samples' time it measures the latest LIVE_KEEP_S of fixes (the newest stretch
first, at most LIVE_SEGMENTS of them across reboots), and speaks once they span LIVE_MIN_SPAN_S and
read past SAY_RATIO at SAY_LAG_S; then it lets go of them.
"""

from __future__ import annotations

import math
from array import array

import numpy as np

from guard.core.aiding.gnss import GnssAiding
from guard.core.ekf import Q_POS_MAX, FilterConfig
from guard.core.geo import LocalFrame
from guard.model.samples import GnssFix
from guard.runtime.every import Live

LAGS_S = (1.0, 2.0, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0)
MAX_GAP_S = 2.0         # s between fixes past which the velocity is not integrated across
LAG_SLACK_S = 0.3       # s: a pair of fixes counts for lag T if they are T apart within this
MIN_PAIRS = 20          # pairs of fixes for a lag's figure
SAY_LAG_S = 10.0        # the lag guard replay says (the small-shift test's time scale)
SAY_RATIO = 1.5         # past this many times the model's, it says what the wander means
SHORT_S, LONG_S = 10.0, 80.0   # the lags whose ratio gives the growth's exponent
LIVE_CHECK_S = 60.0     # guard run measures what it holds this often (the samples' time) ...
LIVE_KEEP_S = 600.0     # ... over the latest this much of it, across reboots (6,000 fixes at 10 Hz) ...
LIVE_SEGMENTS = 3       # ... in at most this many stretches between reboots
LIVE_MIN_SPAN_S = 300.0  # fixes held over this much time before it says anything (30 lags of SAY_LAG_S: the
                        # figure of 12 read some receivers 1.2 times the model past 1.5 at one check)


class PositionWander:
    """A sink: the fixes guard reads with a velocity, and their wander (`measure`)."""

    needs_tests = False

    def __init__(self, filter_cfg: FilterConfig | None = None):
        self.aid = GnssAiding(filter_cfg or FilterConfig())
        self._last: tuple[float, float, float, float] | None = None    # the last fix's lat, lon, east, north
        self.rows = array("d")          # t (s), east, north (m), v_e, v_n (m/s), stretch
        self.sigma = array("d")         # the model's white noise and random walk of each fix
        self.q = array("d")
        self._stretch = 0
        self._t: float | None = None

    def on_sample(self, s) -> None:
        if not (isinstance(s, GnssFix) and s.fix_ok and s.vel_n_mps is not None and s.vel_e_mps is not None):
            return
        t = s.t_us / 1e6
        if self._t is not None and t <= self._t:
            if t > self._t - MAX_GAP_S:             # resent or out of order: left out
                return
            self._stretch += 1                      # the clock went back: a reboot
            self._new_stretch()
        self._t = t
        e = n = 0.0
        if self._last is not None:      # each step in the plane at the fix before it, the one its velocity is in
            lat, lon, e, n = self._last
            de, dn = LocalFrame(lat, lon, 0.0).to_en(s.lat_deg, s.lon_deg)
            e, n = e + de, n + dn
        self._last = (s.lat_deg, s.lon_deg, e, n)
        self.rows.extend((t, e, n, s.vel_e_mps, s.vel_n_mps, self._stretch))
        # its usual figures, which bound what one fix's are taken at: every fix heard (a sink cannot know
        # whether the tests are calm, as the monitor hears only then): a receiver that claims a poor
        # accuracy for over a minute in an attack loosens this model, not the monitor's (it says less)
        self.aid.level.hear(s, True)
        self.sigma.append(self.aid.sigma_pos(s))
        self.q.append(self.aid.q_pos(s))

    def on_events(self, events) -> None:
        pass

    def measure(self, lags=LAGS_S) -> dict | None:
        """{"fixes", "rate_hz", "speed_mps", "sigma_m", "q_pos_m", "lags": [{"lag_s", "wander_m",
        "model_m", "tunable_m"}], "exponent"?}, or None with fewer than MIN_PAIRS fixes. `tunable_m`:
        the model with the largest random walk guard tune fits (`tunable`)."""
        if len(self.sigma) < MIN_PAIRS:
            return None
        a = self._array()
        d = structure(a[:, 0], a[:, 1:3], a[:, 3:5], a[:, 5], lags)
        sigma, q = float(np.median(self.sigma)), float(np.median(self.q))
        q_most = q * tunable(self.aid.f.q_pos_m)
        dt = np.diff(a[:, 0])
        out = {"fixes": len(a), "rate_hz": round(1.0 / float(np.median(dt[dt > 0])), 1) if np.any(dt > 0) else None,
               "speed_mps": round(float(np.median(np.hypot(a[:, 3], a[:, 4]))), 2),
               "sigma_m": round(sigma, 3), "q_pos_m": round(q, 3),
               "lags": [{"lag_s": lag, "wander_m": round(x, 3), "model_m": round(model(sigma, q, lag), 3),
                         "tunable_m": round(model(sigma, q_most, lag), 3)} for lag, x in d.items()]}
        if d.get(SHORT_S) and LONG_S in d:
            out["exponent"] = round(math.log(d[LONG_S] / d[SHORT_S]) / math.log(LONG_S / SHORT_S), 2)
        return out

    def _array(self) -> np.ndarray:
        return np.frombuffer(self.rows, dtype=float).reshape(-1, 6)

    def _new_stretch(self) -> None:
        """A reboot started a new stretch (the whole log's sink keeps every one)."""

    def _keep(self, keep: np.ndarray) -> None:
        """Hold only the fixes where keep is True."""
        if keep.all():
            return
        self.rows = array("d", self._array()[keep].ravel().tolist())
        self.sigma = array("d", np.asarray(self.sigma)[keep].tolist())
        self.q = array("d", np.asarray(self.q)[keep].tolist())


class LivePositionWander(Live, PositionWander):
    """guard run's position wander (a sink): `say(line)` once, where the latest LIVE_KEEP_S of fixes,
    spanning LIVE_MIN_SPAN_S at least, wander past SAY_RATIO times the model at SAY_LAG_S (see the
    module's docstring). `checked`: the last ratio (None: not measured), made at `checked_us`."""

    def __init__(self, say, filter_cfg: FilterConfig | None = None):
        super().__init__(filter_cfg)
        self.live(say, LIVE_CHECK_S)
        self.checked: float | None = None
        self.checked_us: int | None = None

    def ticks(self, s) -> bool:
        return isinstance(s, GnssFix)

    def check(self, t_us: int) -> None:
        """Measure what it holds at t_us (after letting go of what is older than LIVE_KEEP_S); say the
        line where it shows a wander past the model."""
        self._trim(t_us / 1e6)
        a = self._array()
        span = sum(float(np.ptp(a[a[:, 5] == k, 0])) for k in np.unique(a[:, 5])) if len(a) else 0.0
        got = self.measure((SAY_LAG_S,)) if span >= LIVE_MIN_SPAN_S else None
        self.checked, self.checked_us = ratio_at(got), t_us
        if self.checked is None or self.checked <= SAY_RATIO:
            return
        at = got["lags"][0]
        meaning = "a receiver fault or a spoof, past the largest walk guard tune fits" if beyond_tune(got) else \
            "its position alarms may be its own (guard tune fits it)"
        self.tell(t_us, f"GNSS position wanders {at['wander_m']:.2f} m over {SAY_LAG_S:g} s from its own velocity, "
                  f"{self.checked:.1f}x guard's model: {meaning}")

    def let_go(self) -> None:
        self.rows, self.sigma, self.q = array("d"), array("d"), array("d")

    def _trim(self, t: float) -> None:
        """Hold the latest LIVE_KEEP_S of the samples' time at t: the newest stretch back from t, then each
        older one back from its own end, for what is left; at most LIVE_SEGMENTS stretches."""
        a = self._array()
        if not len(a):
            return
        keep = np.zeros(len(a), dtype=bool)
        left = LIVE_KEEP_S
        for i, k in enumerate(np.unique(a[:, 5])[::-1][:LIVE_SEGMENTS]):
            mine = a[:, 5] == k
            end = t if i == 0 else float(a[mine, 0].max())
            if left <= 0.0:
                break
            inside = mine & (a[:, 0] >= end - left)
            keep |= inside
            if inside.any():
                left -= end - float(a[inside, 0].min())
        del a
        self._keep(keep)

    def _new_stretch(self) -> None:
        """A boot loop that never reaches a check holds no more than LIVE_SEGMENTS stretches."""
        keep = self._array()[:, 5] > self._stretch - LIVE_SEGMENTS
        self._keep(keep)


def structure(t: np.ndarray, en: np.ndarray, v: np.ndarray, stretch: np.ndarray | None = None,
              lags=LAGS_S) -> dict[float, float]:
    """D(T) (m, per axis) of position less its velocity's integral, for each lag with MIN_PAIRS pairs of
    fixes T apart within one stretch (of one clock, without a gap over MAX_GAP_S). t increasing within
    each stretch."""
    stretch = np.zeros(len(t)) if stretch is None else np.asarray(stretch)
    dt = np.diff(t)
    inc = 0.5 * (v[1:] + v[:-1]) * dt[:, None]
    broken = (dt > MAX_GAP_S) | (dt <= 0.0) | (np.diff(stretch) != 0)
    inc[broken] = 0.0
    slow = en - np.vstack([[0.0, 0.0], np.cumsum(inc, axis=0)])
    piece = np.concatenate([[0], np.cumsum(broken)])
    out = {}
    for lag in lags:
        j = np.empty(len(t), dtype=int)
        for p in np.unique(piece):          # pairs within one piece, found by its own times
            idx = np.nonzero(piece == p)[0]
            j[idx] = idx[0] + np.searchsorted(t[idx], t[idx] + lag - LAG_SLACK_S)
        i = np.nonzero(j < len(t))[0]
        j = j[i]
        pair = (piece[i] == piece[j]) & (np.abs(t[j] - t[i] - lag) <= LAG_SLACK_S)
        if np.count_nonzero(pair) < MIN_PAIRS:
            continue
        d = slow[j[pair]] - slow[i[pair]]
        out[lag] = float(math.sqrt(np.mean(d * d) / 2.0))
    return out


def model(sigma: float, q: float, lag: float) -> float:
    """D(T) of white noise sigma plus a random walk q (m/sqrt(s)), per axis."""
    return math.sqrt(sigma * sigma + q * q * lag / 2.0)


def tunable(q_pos_m: float) -> float:
    """How many times the configured random walk q_pos_m guard tune raises it at the most: as its
    position_walk does for a wander beyond any bound, up to Q_POS_MAX times the default, never lowered
    (tests/unit/test_position_wander.py holds the two together)."""
    return max(Q_POS_MAX * FilterConfig().q_pos_m, q_pos_m) / q_pos_m


def beyond_tune(result: dict | None, lag: float = SAY_LAG_S) -> bool:
    """Whether the wander at `lag` is further than the largest random walk guard tune fits allows (and
    past SAY_RATIO): no walk of a receiver's own slow error covers it, and its position is faulty or
    attacked (glitches of tens of metres, a spoof's jumps), not a model to tune."""
    at = next((r for r in (result or {}).get("lags", ()) if r["lag_s"] == lag), None)
    return at is not None and at["wander_m"] > max(at["tunable_m"], SAY_RATIO * at["model_m"])


def ratio_at(result: dict | None, lag: float = SAY_LAG_S) -> float | None:
    """The wander over the model's at a lag (None where it was not measured)."""
    return next((r["wander_m"] / r["model_m"] for r in (result or {}).get("lags", ()) if r["lag_s"] == lag), None)


def said(result: dict | None) -> str | None:
    """guard replay's line: the wander at SAY_LAG_S against the model's, and what it means past SAY_RATIO."""
    at = next((r for r in (result or {}).get("lags", ()) if r["lag_s"] == SAY_LAG_S), None)
    if at is None:
        return None
    ratio = at["wander_m"] / at["model_m"]
    line = (f"the receiver's position against its own velocity: it wanders {at['wander_m']:.2f} m over "
            f"{SAY_LAG_S:g} s (per axis), {ratio:.1f} times what guard's model of it allows")
    if beyond_tune(result):
        line += (f": further than the largest walk guard tune fits allows ({at['tunable_m']:.2f} m), so not the "
                 "receiver's usual wander but a fault or a spoof (glitches, jumps), which its position alarms are right "
                 "to flag (tuned on, it would blunt the position's test)")
    elif ratio > SAY_RATIO:
        line += (": its position alarms may be its own wander (guard tune fits the model's random walk, "
                 "filter.q_pos_m, to its clean logs)")
    return line
