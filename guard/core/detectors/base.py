"""The detector interface: what the monitor calls, and what every detector keeps for grd_ratio."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DetectorConfig:
    name: str = "cusum"                 # "cusum" | "paper" | "gate" | "chi2"
    false_alarm_interval_h: float = 1000.0   # cusum: target mean time between false alarms, all channels
    shift_sigma: tuple[float, ...] = (1.0, 4.0)   # cusum: design shifts delta (sigmas), one CUSUM each
    shock_sigma: float = 5.0            # cusum: an IMU innovation counts for at most this many sigmas (0: no bound)
    paper_kappa: float = 3.0            # paper: half-width of the band, in standard deviations of a sum
    paper_warmup: int = 10              # paper: samples that set the band after each (re)start
    gate_sigma: float = 5.0             # gate: an innovation beyond this many sigmas is rejected ...
    gate_persist_s: float = 1.0         # gate: ... and rejection for this long raises the alarm


class Detector(ABC):
    """One statistic per channel of each sensor's innovation.

    `test(sensor, t_us, r, S)` takes the innovation r = y - ŷ (shape (m,)) and its covariance S (m, m)
    and returns (statistics, thresholds, hits): one statistic and threshold per channel, and for
    each channel that rejected H0 at this sample (channel index, estimated shift). `peak` keeps the
    largest statistic / threshold of each sensor over the run (the margin a clean log leaves), where
    the detector has one; `run_length` the samples of the last alarm's run (its onset), where the
    detector can tell.
    """

    name = ""
    peak: dict[str, float] = {}
    run_length: dict[str, int] = {}

    @abstractmethod
    def test(self, sensor: str, t_us: int, r: np.ndarray, S: np.ndarray):
        """(statistics, thresholds, hits) of one sensor's innovation."""

    @abstractmethod
    def take_peak(self) -> float:
        """The largest statistic / threshold since the last call, over every channel."""

    @abstractmethod
    def forget(self, sensor: str) -> None:
        """Restart one sensor's test (it was re-admitted)."""

    @abstractmethod
    def reset(self) -> None:
        """Restart every test (the filter was re-initialised)."""


class _Peaks(Detector):
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
