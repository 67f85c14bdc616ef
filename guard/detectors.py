"""Change detectors on the filter's innovations, one statistic per channel.

Each detector has one method, `test(sensor, t_us, r, S)`, which takes the innovation r = y - ŷ of
one sensor (shape (m,)) and its covariance S (m, m), and returns the statistic and threshold of each
channel and the indices of the channels that rejected H0 at this sample (with the estimated shift).

`paper`: the two-sided CUSUM of the paper (eq. 11) exactly as written,
    S(k+1) = max(0, S(k) + |r(k+1)|)  while S(k) <= tau(k);  else S = 0 and k_alpha = k.
It has no drift term, so under H0 S grows like n E|r|: it only works against a growing threshold.
The paper builds its band "from the weighted sum of the first 10 samples"; we read that as
    tau(n) = n m + kappa s sqrt(n),
n the samples since the (re)start, m and s the mean and standard deviation of |r| over the first
10 of them: the centre is the first 10 samples' sum scaled by n/10, the half-width the spread of a
sum of n such samples. No decision is taken in those first 10 samples (the paper's blind start).

`gate` and `chi2` are the baselines a detector must beat: the autopilots' 5-sigma innovation gate
with a persistence rule, and a memoryless chi-square test of each sensor's innovation.

`cusum`: Page's two-sided CUSUM on the normalised innovation z = r / sqrt(S_ii),
    g+(k) = max(0, g+(k-1) + z(k) - k_ref),   g-(k) = max(0, g-(k-1) - z(k) - k_ref),
alarm when max(g+, g-) > h. k_ref = delta/2 for a design shift of delta sigmas, one CUSUM per
design shift in a bank (default 1 and 4 sigmas: unknown attack sizes); h is set from a
target mean time between false alarms (all channels together) with Siegmund's approximation of
the in-control average run length, ARL0(h) = (exp(2 k (h + 1.166)) - 2 k (h + 1.166) - 1) / (2 k^2).
Against the exact ARL0 (Page's integral equation, checked in the tests) the approximation is
within 1 % at k = 0.5 and overstates it by half at k = 2 (exact 0.66 of it): on white innovations
the default bank's real mean time between false alarms is about 0.8 of the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np


@dataclass(frozen=True)
class DetectorConfig:
    name: str = "cusum"                 # "cusum" | "paper" | "gate" | "chi2"
    false_alarm_interval_h: float = 1000.0   # cusum: target mean time between false alarms, all channels
    shift_sigma: tuple[float, ...] = (1.0, 4.0)   # cusum: design shifts delta (sigmas), one CUSUM each
    paper_kappa: float = 3.0            # paper: half-width of the band, in standard deviations of a sum
    paper_warmup: int = 10              # paper: samples that set the band after each (re)start
    gate_sigma: float = 5.0             # gate: an innovation beyond this many sigmas is rejected ...
    gate_persist_s: float = 1.0         # gate: ... and rejection for this long raises the alarm


def siegmund_arl(h: float, k: float) -> float:
    """In-control ARL of a one-sided CUSUM on N(0,1) data with reference k and threshold h."""
    a = 2.0 * k * (h + 1.166)
    return (math.exp(a) - a - 1.0) / (2.0 * k * k)


def threshold_for_arl(arl0: float, k: float) -> float:
    """The h at which siegmund_arl(h, k) = arl0 (bisection)."""
    lo, hi = 0.0, 1.0
    while siegmund_arl(hi, k) < arl0:
        hi *= 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if siegmund_arl(mid, k) < arl0 else (lo, mid)
    return 0.5 * (lo + hi)


class _Page:
    """One channel of a bank of two-sided Page CUSUMs, one per reference value k."""

    __slots__ = ("gp", "gn", "sum_p", "sum_n", "cnt_p", "cnt_n")

    def __init__(self, n: int):
        self.gp, self.gn = [0.0] * n, [0.0] * n
        self.sum_p, self.sum_n = [0.0] * n, [0.0] * n      # sums of r while g > 0: the shift estimate
        self.cnt_p, self.cnt_n = [0] * n, [0] * n


class PageCusum:
    """A bank of Page CUSUMs per channel, one per design shift in `shift_sigma` (k = shift / 2).

    A small shift accumulates in the small-k member, a large step fires the large-k member at once:
    together they cover an attack of unknown size. All members of all channels share the budget.
    The statistic reported for a channel is that of the member closest to its threshold.
    """

    name = "cusum"

    def __init__(self, cfg: DetectorConfig, n_channels: int):
        self.cfg = cfg
        self.ks = [d / 2.0 for d in cfg.shift_sigma]
        self.n_tests = 2 * n_channels * len(self.ks)    # two sides per channel and member share the budget
        self.state: dict[str, list[_Page]] = {}
        self.h: dict[str, list[float]] = {}
        self._first_t: dict[str, int] = {}
        self.peak: dict[str, float] = {}                # sensor -> largest statistic / threshold seen
        self.run_length: dict[str, int] = {}            # sensor -> samples in the last alarm's run: its onset
        self.recent = 0.0                               # largest statistic / threshold since take_peak()

    def threshold(self, rate_hz: float) -> list[float]:
        """h of each member, for one side of one channel sampled at rate_hz."""
        arl0 = self.cfg.false_alarm_interval_h * 3600.0 * rate_hz * self.n_tests
        return [threshold_for_arl(arl0, k) for k in self.ks]

    def _h(self, sensor: str, t_us: int) -> list[float]:
        """h from the sensor's rate, known at its second sample (a 50 Hz guess before that)."""
        h = self.h.get(sensor)
        if h is None:
            t0 = self._first_t.setdefault(sensor, t_us)
            if t_us <= t0:
                return self.threshold(50.0)
            h = self.h[sensor] = self.threshold(min(1000.0, 1e6 / (t_us - t0)))
        return h

    def test(self, sensor: str, t_us: int, r: np.ndarray, S: np.ndarray):
        chans = self.state.get(sensor)
        nk = len(self.ks)
        if chans is None:
            chans = self.state[sensor] = [_Page(nk) for _ in range(len(r))]
        hs = self._h(sensor, t_us)
        stat, thr, alarms = [], [], []
        onset = 0                                       # the longest run of this sample's alarms
        for i, (ri, si) in enumerate(zip(r.tolist(), S.diagonal().tolist())):
            c = chans[i]
            z = ri / math.sqrt(si)
            best, best_j, best_g = -1.0, 0, 0.0
            for j, k in enumerate(self.ks):
                # g+ = max(0, g+ + z - k),  g- = max(0, g- - z - k)
                gp = c.gp[j] + z - k
                if gp > 0.0:
                    c.gp[j] = gp; c.sum_p[j] += ri; c.cnt_p[j] += 1
                else:
                    gp = c.gp[j] = c.sum_p[j] = 0.0; c.cnt_p[j] = 0
                gn = c.gn[j] - z - k
                if gn > 0.0:
                    c.gn[j] = gn; c.sum_n[j] += ri; c.cnt_n[j] += 1
                else:
                    gn = c.gn[j] = c.sum_n[j] = 0.0; c.cnt_n[j] = 0
                g = gp if gp > gn else gn
                if g / hs[j] > best:
                    best, best_j, best_g = g / hs[j], j, g
            j = best_j
            if best > self.peak.get(sensor, 0.0):
                self.peak[sensor] = best
            if best > self.recent:
                self.recent = best
            stat.append(best_g)
            thr.append(hs[j])
            if best > 1.0:
                up = c.gp[j] >= c.gn[j]
                n = c.cnt_p[j] if up else c.cnt_n[j]
                alarms.append((i, (c.sum_p[j] if up else c.sum_n[j]) / n))
                onset = self.run_length[sensor] = max(onset, n)
                chans[i] = _Page(nk)      # the test restarts after an alarm
        return tuple(stat), tuple(thr), alarms

    def ratio(self) -> float:
        """The largest statistic / threshold over every channel and member now (1.0 = at the threshold)."""
        return max((max(c.gp[j], c.gn[j]) / self.h[s][j] for s, chans in self.state.items() if s in self.h
                    for c in chans for j in range(len(self.ks))), default=0.0)

    def take_peak(self) -> float:
        """The largest statistic / threshold since the last call, over every channel and member."""
        peak, self.recent = self.recent, 0.0
        return peak

    def forget(self, sensor: str) -> None:
        """Restart one sensor's test (it was re-admitted); its threshold stays."""
        self.state.pop(sensor, None)

    def reset(self) -> None:
        self.state.clear()
        self.h.clear()
        self._first_t.clear()


class _Peaks:
    """grd_ratio for the baselines: the largest statistic / threshold since take_peak()."""

    recent = 0.0

    def _seen(self, stat, thr):
        for g, h in zip(stat, thr):
            if 0.0 < h < math.inf and g / h > self.recent:
                self.recent = g / h
        return tuple(stat), tuple(thr)

    def take_peak(self) -> float:
        peak, self.recent = self.recent, 0.0
        return peak


class _Band:
    """One channel of the paper's CUSUM and its band."""

    __slots__ = ("S", "n", "s1", "s2", "mean", "std")

    def __init__(self):
        self.S = 0.0
        self.n = 0
        self.s1 = self.s2 = 0.0     # sums of |r| and |r|^2 over the warm-up
        self.mean = self.std = 0.0


class PaperCusum(_Peaks):
    name = "paper"

    def __init__(self, cfg: DetectorConfig, n_channels: int):
        self.cfg = cfg
        self.state: dict[str, list[_Band]] = {}

    def test(self, sensor: str, t_us: int, r: np.ndarray, S: np.ndarray):
        chans = self.state.get(sensor)
        if chans is None:
            chans = self.state[sensor] = [_Band() for _ in range(len(r))]
        n0, kappa = self.cfg.paper_warmup, self.cfg.paper_kappa
        stat, thr, alarms = [], [], []
        for i, ri in enumerate(r.tolist()):
            c, a = chans[i], abs(ri)
            # S(k+1) = max(0, S(k) + |r(k+1)|)
            c.S = max(0.0, c.S + a)
            c.n += 1
            stat.append(c.S)
            if c.n <= n0:
                c.s1 += a
                c.s2 += a * a
                if c.n == n0:
                    c.mean = c.s1 / n0
                    c.std = math.sqrt(max(c.s2 / n0 - c.mean ** 2, 0.0))
                thr.append(math.inf)
                continue
            # tau(n) = n m + kappa s sqrt(n)
            tau = c.n * c.mean + kappa * c.std * math.sqrt(c.n)
            thr.append(tau)
            if c.S > tau:
                alarms.append((i, ri))
                chans[i] = _Band()      # restart: S = 0, a new band from the next samples
        return *self._seen(stat, thr), alarms

    def forget(self, sensor: str) -> None:
        self.state.pop(sensor, None)

    def reset(self) -> None:
        self.state.clear()


class Gate(_Peaks):
    """The autopilots' rule: reject an innovation beyond `gate_sigma`; alarm when a channel has been
    rejected on every sample for `gate_persist_s` (ArduPilot and PX4 then reset onto the GNSS)."""

    name = "gate"

    def __init__(self, cfg: DetectorConfig, n_channels: int):
        self.cfg = cfg
        self.since: dict[tuple[str, int], int] = {}     # (sensor, channel) -> first rejected sample time

    def test(self, sensor: str, t_us: int, r: np.ndarray, S: np.ndarray):
        g, stat, alarms = self.cfg.gate_sigma, [], []
        persist = self.cfg.gate_persist_s * 1e6
        for i, (ri, si) in enumerate(zip(r.tolist(), S.diagonal().tolist())):
            z = abs(ri) / math.sqrt(si)
            key = (sensor, i)
            if z <= g:
                self.since.pop(key, None)
                stat.append(0.0)
                continue
            t0 = self.since.setdefault(key, t_us)
            stat.append((t_us - t0) / 1e6)
            if t_us - t0 >= persist:
                alarms.append((i, ri))
                del self.since[key]
        return *self._seen(stat, (self.cfg.gate_persist_s,) * len(stat)), alarms

    def forget(self, sensor: str) -> None:
        for key in [k for k in self.since if k[0] == sensor]:
            del self.since[key]

    def reset(self) -> None:
        self.since.clear()


class ChiSquare(_Peaks):
    """A memoryless test per sensor: NIS = rᵀ S⁻¹ r against the chi-square quantile whose tail
    probability gives the target mean time between false alarms. The alarm names the channel with
    the largest normalised innovation."""

    name = "chi2"

    def __init__(self, cfg: DetectorConfig, n_channels: int):
        self.cfg = cfg
        self.n_tests = n_channels
        self.h: dict[str, float] = {}
        self._first_t: dict[str, int] = {}

    def _h(self, sensor: str, t_us: int, m: int) -> float:
        h = self.h.get(sensor)
        if h is None:
            t0 = self._first_t.setdefault(sensor, t_us)
            rate = 50.0 if t_us <= t0 else min(1000.0, 1e6 / (t_us - t0))
            p = 1.0 / (self.cfg.false_alarm_interval_h * 3600.0 * rate * self.n_tests)
            h = chi2_quantile(p, m)
            if t_us > t0:
                self.h[sensor] = h
        return h

    def test(self, sensor: str, t_us: int, r: np.ndarray, S: np.ndarray):
        h = self._h(sensor, t_us, len(r))
        nis = float(r @ np.linalg.solve(S, r))
        alarms = []
        if nis > h:
            z = np.abs(r) / np.sqrt(np.diagonal(S))
            i = int(np.argmax(z))
            alarms.append((i, float(r[i])))
        return *self._seen((nis,) * len(r), (h,) * len(r)), alarms

    def forget(self, sensor: str) -> None:
        pass            # memoryless

    def reset(self) -> None:
        self.h.clear()
        self._first_t.clear()


def chi2_quantile(p: float, dof: int) -> float:
    """x with P(chi2_dof > x) = p, for dof 1 (from the normal quantile) and 2 (closed form)."""
    if dof == 1:
        return NormalDist().inv_cdf(1.0 - p / 2.0) ** 2
    if dof == 2:
        return -2.0 * math.log(p)
    raise ValueError("chi2_quantile: dof must be 1 or 2")


DETECTORS = {"cusum": PageCusum, "paper": PaperCusum, "gate": Gate, "chi2": ChiSquare}


def make_detector(cfg: DetectorConfig, n_channels: int):
    return DETECTORS[cfg.name](cfg, n_channels)
