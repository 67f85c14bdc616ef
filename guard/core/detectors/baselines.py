"""The baselines a detector must beat: the autopilots' innovation gate and a chi-square test."""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np

from guard.core.detectors.base import DetectorConfig, TestRate, _Peaks


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
        self.h: dict[tuple[str, int], float] = {}
        self.rate: dict[str, float] = {}
        self.rates = TestRate()

    def _h(self, sensor: str, t_us: int, m: int) -> float:
        """h from the sensor's rate (TestRate), for m channels."""
        rate = self.rates.add(sensor, t_us)
        if rate is not None:
            self.rate[sensor] = rate
            self.h = {k: v for k, v in self.h.items() if k[0] != sensor}
        h = self.h.get((sensor, m))
        if h is None:
            p = 1.0 / (self.cfg.false_alarm_interval_h * 3600.0 * self.rate[sensor] * self.n_tests)
            h = self.h[(sensor, m)] = chi2_quantile(p, m)
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
        self.rate.clear()
        self.rates.reset()


def chi2_quantile(p: float, dof: int) -> float:
    """x with P(chi2_dof > x) = p, for dof 1 (from the normal quantile), 2 (closed form) and 3 (its tail,
    2 (1 - Phi(sqrt x)) + sqrt(2 x / pi) exp(-x / 2), solved by bisection)."""
    if dof == 1:
        return NormalDist().inv_cdf(1.0 - p / 2.0) ** 2
    if dof == 2:
        return -2.0 * math.log(p)
    if dof == 3:
        def tail(x: float) -> float:
            return 2.0 * (1.0 - NormalDist().cdf(math.sqrt(x))) + math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0)
        lo, hi = 0.0, 1.0
        while tail(hi) > p:
            hi *= 2.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if tail(mid) > p else (lo, mid)
        return 0.5 * (lo + hi)
    raise ValueError("chi2_quantile: dof must be 1, 2 or 3")
