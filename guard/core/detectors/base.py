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


GUESS_HZ = 50.0         # a sensor's rate before its second sample
MAX_HZ = 1000.0         # the most a rate is taken for
RATE_SAMPLES = 20       # from this many samples on, the rate is 1 / the median of their intervals


class TestRate:
    """Each sensor's sampling rate, as its tests' thresholds need it (their false-alarm budget is per
    hour, so per sample at that rate): GUESS_HZ before its second sample, then 1 / the first interval,
    then, from its RATE_SAMPLES-th sample on and for good, 1 / the median of the positive intervals
    between its first RATE_SAMPLES. The first interval alone is what a regular stream gives from the
    start; a log's first two samples can come milliseconds apart (a fix sent twice) or seconds apart (a
    receiver starting), which on real logs set a 5 Hz receiver's thresholds as at 52.6 Hz, and a 1 Hz
    one's as at 0.6 Hz, for the whole run; the median holds the stream's own rate through both, and
    through close stamps while they are fewer than half of the intervals. Where the threshold falls at the
    RATE_SAMPLES-th sample (its first interval shorter than the stream's), a statistic already past the
    new one alarms there, as it would have by then at the stream's own rate. The monitor gives a
    detector increasing stamps (its time base drops resent and out-of-order samples)."""

    def __init__(self):
        self._times: dict[str, list[int]] = {}      # sensor -> its first samples' times
        self._final: set[str] = set()

    def add(self, sensor: str, t_us: int) -> float | None:
        """The rate at this sample where it has changed (GUESS_HZ at the first sample, then at the
        first one later than it, and at the RATE_SAMPLES-th), else None."""
        if sensor in self._final:
            return None
        times = self._times.setdefault(sensor, [])
        times.append(t_us)
        if len(times) == 1:
            return GUESS_HZ
        if len(times) >= RATE_SAMPLES:
            self._final.add(sensor)
            del self._times[sensor]
            steps = sorted(b - a for a, b in zip(times, times[1:]) if b > a)
            if steps:
                return min(MAX_HZ, 1e6 / steps[(len(steps) - 1) // 2])
            return None
        later = [t for t in times if t > times[0]]
        if len(later) == 1 and t_us > times[0]:         # the first sample later than the first
            return min(MAX_HZ, 1e6 / (t_us - times[0]))
        return None

    def reset(self) -> None:
        self._times.clear()
        self._final.clear()


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
