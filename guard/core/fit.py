"""Does the model fit the vehicle? The innovations of a well-modelled sensor, normalised by their
covariance (z = r_i / sqrt(S_ii)), have unit variance. Over minutes, per sensor, the mean of z^2 of
the fused innovations (each clipped at CLIP^2, so that one glitch does not speak for minutes) says by
how much the noise model is off. A model that does not fit is said as a WARNING naming the sensor
and the factor ("gnss_vel innovations 2.3x the model: run guard tune"), not as an attack alarm; it is
said again only when the factor grew by REPEAT_GROWTH, or after REPEAT_S.
"""

from __future__ import annotations

import math

import numpy as np

from guard.model.events import Notice
from guard.model.sensors import Sensor

TAU_S = 300.0           # s, the memory of the mean (exponential forgetting)
MATURE_S = 120.0        # s of a sensor's innovations before its fit is judged
WARN_FACTOR = 1.5       # innovations this many times the model's standard deviation
CLIP = 5.0
REPEAT_S = 600.0
REPEAT_GROWTH = 1.25


class ModelFit:
    def __init__(self):
        self.sum: dict[Sensor, float] = {}          # decayed sums of z^2 and of the channel count
        self.n: dict[Sensor, float] = {}
        self.t0: dict[Sensor, int] = {}
        self.t: dict[Sensor, int] = {}
        self.said: dict[Sensor, tuple[int, float]] = {}    # when a warning went out, and its factor

    def add(self, sensor: Sensor, t_us: int, r: np.ndarray, S: np.ndarray) -> None:
        z2 = np.minimum(np.square(r) / np.diagonal(S), CLIP * CLIP)
        last = self.t.get(sensor)
        decay = 1.0 if last is None else math.exp(-(t_us - last) / (TAU_S * 1e6))
        self.sum[sensor] = self.sum.get(sensor, 0.0) * decay + float(z2.sum())
        self.n[sensor] = self.n.get(sensor, 0.0) * decay + len(z2)
        self.t[sensor] = t_us
        self.t0.setdefault(sensor, t_us)

    def factor(self, sensor: Sensor) -> float | None:
        """sqrt(mean z^2): 1 when the model fits; None before MATURE_S of innovations."""
        if sensor not in self.t or self.t[sensor] - self.t0[sensor] < MATURE_S * 1e6:
            return None
        return math.sqrt(self.sum[sensor] / self.n[sensor])

    def check(self, t_us: int) -> list[Notice]:
        out = []
        for sensor in self.t:
            f = self.factor(sensor)
            if f is None or f < WARN_FACTOR:
                continue
            when, said = self.said.get(sensor, (None, 0.0))
            if when is not None and f < said * REPEAT_GROWTH and t_us - when < REPEAT_S * 1e6:
                continue
            self.said[sensor] = (t_us, f)
            out.append(Notice(t_us, "warning", f"{sensor} innovations {f:.1f}x the model: run guard tune"))
        return out
