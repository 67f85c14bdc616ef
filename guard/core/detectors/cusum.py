"""Page's two-sided CUSUM, a bank of design shifts per channel; its threshold from Siegmund's ARL."""

from __future__ import annotations

import math

import numpy as np

from guard.core.detectors.base import Detector, DetectorConfig, TestRate


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


class PageCusum(Detector):
    """A bank of Page CUSUMs per channel, one per design shift in `shift_sigma` (k = shift / 2).

    A small shift accumulates in the small-k member, a large step fires the large-k member at once:
    together they cover an attack of unknown size. All members of all channels share the budget.
    The statistic reported for a channel is that of the member closest to its threshold.

    The inertial sensors' normalised innovations count for at most `shock_sigma` (Huber's bounded
    CUSUM): an accelerometer and a gyro measure real shocks (a landing, the motors' start, a kerb) of
    many sigmas for a sample or two, which no Gaussian model of their noise covers, and an attack on
    them matters by persisting (a bias moves the estimate only as it integrates). One sample adds at
    most shock_sigma - k, under the threshold: a shock needs company to alarm, a bias of any size
    still accumulates every sample. Bounding can only lower the in-control statistic, so the
    thresholds (Siegmund's, for N(0, 1) data) keep their false-alarm budget.
    """

    BOUNDED = frozenset({"accel", "gyro"})

    name = "cusum"

    def __init__(self, cfg: DetectorConfig, n_channels: int):
        self.cfg = cfg
        self.ks = [d / 2.0 for d in cfg.shift_sigma]
        self.n_tests = 2 * n_channels * len(self.ks)    # two sides per channel and member share the budget
        self.state: dict[str, list[_Page]] = {}
        self.h: dict[str, list[float]] = {}
        self.rates = TestRate()
        self.peak: dict[str, float] = {}                # sensor -> largest statistic / threshold seen
        self.run_length: dict[str, int] = {}            # sensor -> samples in the last alarm's run: its onset
        self.recent = 0.0                               # largest statistic / threshold since take_peak()

    def threshold(self, rate_hz: float) -> list[float]:
        """h of each member, for one side of one channel sampled at rate_hz."""
        arl0 = self.cfg.false_alarm_interval_h * 3600.0 * rate_hz * self.n_tests
        return [threshold_for_arl(arl0, k) for k in self.ks]

    def _h(self, sensor: str, t_us: int) -> list[float]:
        """h from the sensor's rate (TestRate: a guess, its first interval, then its first samples' median interval)."""
        rate = self.rates.add(sensor, t_us)
        if rate is not None:
            self.h[sensor] = self.threshold(rate)
        return self.h[sensor]

    def test(self, sensor: str, t_us: int, r: np.ndarray, S: np.ndarray):
        chans = self.state.get(sensor)
        ks = self.ks
        nk = len(ks)
        if chans is None or len(chans) != len(r):      # new, or its channels changed (a vehicle found on wheels)
            chans = self.state[sensor] = [_Page(nk) for _ in range(len(r))]
        hs = self._h(sensor, t_us)
        clip = self.cfg.shock_sigma if sensor in self.BOUNDED and self.cfg.shock_sigma > 0 else math.inf
        stat, thr, alarms = [], [], []
        onset = 0                                       # the longest run of this sample's alarms
        for i, (ri, si) in enumerate(zip(r.tolist(), S.diagonal().tolist())):
            c = chans[i]
            gps, gns, sum_p, sum_n, cnt_p, cnt_n = c.gp, c.gn, c.sum_p, c.sum_n, c.cnt_p, c.cnt_n
            # z = r / sqrt(S_ii), within [-clip, clip]
            z = ri / math.sqrt(si)
            if z > clip:
                z = clip
            elif z < -clip:
                z = -clip
            best, best_j, best_g = -1.0, 0, 0.0
            for j in range(nk):
                k = ks[j]
                # g+ = max(0, g+ + z - k),  g- = max(0, g- - z - k)
                gp = gps[j] + z - k
                if gp > 0.0:
                    gps[j] = gp; sum_p[j] += ri; cnt_p[j] += 1
                else:
                    gp = gps[j] = sum_p[j] = 0.0; cnt_p[j] = 0
                gn = gns[j] - z - k
                if gn > 0.0:
                    gns[j] = gn; sum_n[j] += ri; cnt_n[j] += 1
                else:
                    gn = gns[j] = sum_n[j] = 0.0; cnt_n[j] = 0
                g = gp if gp > gn else gn
                ratio = g / hs[j]
                if ratio > best:
                    best, best_j, best_g = ratio, j, g
            j = best_j
            if best > self.peak.get(sensor, 0.0):
                self.peak[sensor] = best
            if best > self.recent:
                self.recent = best
            stat.append(best_g)
            thr.append(hs[j])
            if best > 1.0:
                up = gps[j] >= gns[j]
                n = cnt_p[j] if up else cnt_n[j]
                alarms.append((i, (sum_p[j] if up else sum_n[j]) / n))
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
        self.rates.reset()
