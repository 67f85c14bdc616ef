"""The paper's CUSUM (eq. 11) as written, against a growing band (see the package's docstring)."""

from __future__ import annotations

import math

import numpy as np

from guard.core.detectors.base import DetectorConfig, _Peaks


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
        if chans is None or len(chans) != len(r):      # new, or its channels changed (a vehicle found on wheels)
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
