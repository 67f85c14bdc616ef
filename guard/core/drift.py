"""How far this vehicle's IMU alone strays: its open-loop drift, measured in flight.

While the GNSS is excluded the estimate coasts on the IMU, and the exclusion ends when the filter's own
uncertainty passes `max_coast_m` (guard.core.judge.Judge.reanchor). That uncertainty is the model's: the
levelled accelerometers' errors taken as white noise and a slow bias. A real copter's are neither: the
autopilot's tilt error times g, a compass-held heading a few degrees off under hard acceleration,
vibration rectified; each lasts seconds, and a correlated error is integrated twice where white noise
is integrated once. On the real copters of the README that coasted, the estimate stood a median of up to
6 times its 1 sigma from the fixes (14 at the 90th percentile on a hard-flown one, 97 m against a
claimed 19), and was re-anchored up to 180 m from them.

So the drift is measured, on the vehicle, while there is a GNSS to measure it against. Every
PROBE_EVERY_S, at a fix fused with every test calm, a probe starts from the filter's estimate (position,
ground velocity, accelerometer biases) and dead-reckons on the IMU alone as a coast would: the levelled
specific force less the biases, turned to east-north by the filter's heading, integrated twice. At each
fix for PROBE_S after, its distance from the fix is one sample of the drift at that age (taken only
while every test is calm). `sigma(age)` is their root mean square in the age's bin, forgetting over
TAU_S: what an estimate that has coasted that long is worth on this vehicle, in this flight.

The judge takes the larger of the filter's uncertainty and this, the latter at most F_MAX times the
former, on a coast on the IMU alone. An attacker who moves the GNSS while every test stays calm makes
the drift look as large as he moves it: a GNSS moved 14 m back and forth over a minute (0.15 m/s^2,
which a vibrating IMU does not tell from its own wander) ends the coast after his later alarm at once.
That is no more than he could do without it: an offset that large, laid in that slowly, raises no alarm
at all. A wheeled vehicle's coast is held by its sideways constraint, which this dead reckoning has
not: it is measured and applied on air vehicles only (Monitor).
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass

import numpy as np

from guard.core.ekf import BAX, BAY, TH, VX, VY, X, Y

PROBE_EVERY_S = 5.0     # s between probes' starts
PROBE_S = 32.0          # s a probe runs
EDGES_S = (1.0, 2.0, 4.0, 8.0, 16.0, PROBE_S)   # the age bins' edges: [1, 2), [2, 4), ... [16, 32)
TAU_S = 300.0           # s, the memory of each bin's mean square
MIN_PROBES = 3          # probes a bin has measured before it is believed
F_MAX = 4.0             # the most the drift may widen the filter's uncertainty
FORGET = 1.0 - math.exp(-PROBE_EVERY_S / TAU_S)     # each probe's weight once a bin's memory is full
GAP_S = 0.5             # IMU fusions further apart than this are not dead-reckoned across


@dataclass(slots=True)
class Probe:
    """One dead reckoning: where it started (the sums' time), the estimate then and the sums then; and
    the age bin it is in, with the sum and count of its squared distances from the fixes there."""

    t0_us: int
    p0: tuple[float, float]         # position, east and north (m)
    v0: tuple[float, float]         # ground velocity (m/s)
    bias: tuple[float, float]       # the filter's accelerometer biases, forward and left (m/s^2)
    sums0: tuple[float, ...]
    bin: int = -1
    d2: float = 0.0
    count: int = 0


class Drift:
    """The probes share one dead reckoning: the IMU's specific force, turned to east-north by the
    filter's heading, integrated once and twice (V, P), and the rotation itself likewise (C1, S1, C2,
    S2: the integrals of cos and sin of the heading), which carry any one probe's biases. A probe is
    then its start and a snapshot of those eight sums, and its position at any time a few products:
    each IMU fusion costs the same however many probes run."""

    def __init__(self):
        self.sums = [0.0] * 8               # V_e, V_n, P_e, P_n, C1, S1, C2, S2
        self.t_us: int | None = None        # the sums' time (the last IMU fusion)
        self.probes: list[Probe] = []
        self.ms = [0.0] * (len(EDGES_S) - 1)    # each age bin's mean square distance, over probes
        self.n = [0] * (len(EDGES_S) - 1)       # and the probes it has taken
        self._last_start: int | None = None

    def start(self, t_us: int, x: np.ndarray) -> None:
        """At a fix fused with every test calm: a probe from the filter's estimate, every PROBE_EVERY_S."""
        if self.t_us is None or (self._last_start is not None and t_us - self._last_start < PROBE_EVERY_S * 1e6):
            return
        self._last_start = t_us
        cs, sn = math.cos(x[TH]), math.sin(x[TH])
        v0 = (x[VX] * cs - x[VY] * sn, x[VX] * sn + x[VY] * cs)
        # the estimate at the fix's time, carried back to the sums' by its velocity
        back = (t_us - self.t_us) / 1e6
        p0 = (x[X] - v0[0] * back, x[Y] - v0[1] * back)
        self.probes.append(Probe(self.t_us, p0, v0, (float(x[BAX]), float(x[BAY])), tuple(self.sums)))

    def imu(self, t_us: int, ax: float, ay: float, theta: float) -> None:
        """One IMU fusion's levelled specific force (forward, left) and the filter's heading."""
        if self.t_us is not None and t_us - self.t_us > GAP_S * 1e6:
            self.restart()                  # an IMU gap: what it did then is unknown
        if self.t_us is None or t_us <= self.t_us:
            self.t_us = t_us if self.t_us is None else self.t_us
            return
        dt = (t_us - self.t_us) / 1e6
        self.t_us = t_us
        c, s = math.cos(theta), math.sin(theta)
        ae, an = c * ax - s * ay, s * ax + c * ay
        ve, vn, pe, pn, c1, s1, c2, s2 = self.sums
        h = 0.5 * dt * dt
        self.sums = [ve + ae * dt, vn + an * dt, pe + ve * dt + ae * h, pn + vn * dt + an * h,
                     c1 + c * dt, s1 + s * dt, c2 + c1 * dt + c * h, s2 + s1 * dt + s * h]

    def position(self, probe: Probe, t_us: int) -> tuple[float, float]:
        """Where a probe's dead reckoning puts the vehicle at t_us (near the sums' time: carried by its
        velocity from there)."""
        (pe0, pn0), (ve0, vn0), (b1, b2) = probe.p0, probe.v0, probe.bias
        Ve0, Vn0, Pe0, Pn0, C10, S10, C20, S20 = probe.sums0
        t0 = probe.t0_us
        ve, vn, pe, pn, c1, s1, c2, s2 = self.sums
        T = (self.t_us - t0) / 1e6
        dc1, ds1 = c1 - C10, s1 - S10                           # the rotation's integrals since t0
        dc2, ds2 = c2 - C20 - C10 * T, s2 - S20 - S10 * T
        e = pe0 + ve0 * T + (pe - Pe0 - Ve0 * T) - (dc2 * b1 - ds2 * b2)
        n = pn0 + vn0 * T + (pn - Pn0 - Vn0 * T) - (ds2 * b1 + dc2 * b2)
        vel_e = ve0 + (ve - Ve0) - (dc1 * b1 - ds1 * b2)
        vel_n = vn0 + (vn - Vn0) - (ds1 * b1 + dc1 * b2)
        late = (t_us - self.t_us) / 1e6
        return e + vel_e * late, n + vel_n * late

    def fix(self, t_us: int, en: tuple[float, float], calm: bool) -> None:
        """A fix fused, showing the vehicle at t_us: each probe's distance from it, in its age's bin (if
        calm). A probe's bin is taken as one sample, the mean of its distances there, when the probe
        leaves it; probes past PROBE_S end."""
        if self.t_us is None:
            return
        kept = []
        for probe in self.probes:
            age = (t_us - probe.t0_us) / 1e6
            k = bisect_right(EDGES_S, age) - 1
            if k != probe.bin:
                self._take(probe)
                probe.bin = k
            if calm and 0 <= k < len(self.ms):
                e, n = self.position(probe, t_us)
                probe.d2 += (e - en[0]) ** 2 + (n - en[1]) ** 2
                probe.count += 1
            if age < PROBE_S:
                kept.append(probe)
            else:
                self._take(probe)
        self.probes = kept

    def _take(self, probe: Probe) -> None:
        """A probe's bin, measured: its mean square distance there joins the bin's, forgetting over TAU_S."""
        k, total, count = probe.bin, probe.d2, probe.count
        probe.d2, probe.count = 0.0, 0
        if count == 0 or not 0 <= k < len(self.ms):
            return
        self.n[k] += 1
        self.ms[k] += max(1.0 / self.n[k], FORGET) * (total / count - self.ms[k])

    def restart(self) -> None:
        """A gap, a rewind, a re-anchoring or the GNSS excluded: the running probes end (what they measured
        stays)."""
        for probe in self.probes:
            self._take(probe)
        self.probes = []
        self.sums = [0.0] * 8
        self.t_us = None
        self._last_start = None

    def sigma(self, age_s: float) -> float | None:
        """The drift measured at this age (m, rms), or None before any bin is. Between the bins' middles
        it is interpolated on log-log axes; before the first it grows as a velocity error's does (with
        the age), after the last as an acceleration error's (with its square)."""
        known = [k for k, n in enumerate(self.n) if n >= MIN_PROBES]
        if not known or age_s <= 0.0:
            return None
        mids = np.array([math.sqrt(EDGES_S[k] * EDGES_S[k + 1]) for k in known])
        rms = np.sqrt([self.ms[k] for k in known])
        if age_s <= mids[0]:
            return float(rms[0] * age_s / mids[0])
        if age_s >= mids[-1]:
            return float(rms[-1] * (age_s / mids[-1]) ** 2)
        return float(np.exp(np.interp(math.log(age_s), np.log(mids), np.log(np.maximum(rms, 1e-3)))))

    def widened(self, sigma_model: float, age_s: float) -> float:
        """The uncertainty of an estimate that has coasted age_s: the larger of the filter's and the
        drift measured, the latter at most F_MAX times the former."""
        d = self.sigma(age_s)
        return sigma_model if d is None else max(sigma_model, min(d, F_MAX * sigma_model))

