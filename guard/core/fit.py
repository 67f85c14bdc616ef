"""Does the model fit the vehicle? The innovations of a well-modelled sensor, normalised by their
covariance (z = r_i / sqrt(S_ii)), have unit variance. Over minutes, per sensor, the mean of z^2 of
the fused innovations (each clipped at CLIP^2, so that one glitch does not speak for minutes; a held
course's, whose error is the course it repeats, left out: Innovation.modelled) says by
how much the noise model is off. A model that does not fit is said as a WARNING naming the sensor
and the factor ("gnss_vel innovations 2.3x the model: run guard tune"), not as an attack alarm; it is
said again only when the factor grew by REPEAT_GROWTH, or after REPEAT_S. On wheels the
accelerometer's test holds the sideways constraint's channel too, whose noise is its own
(`lateral_sigma_mps`): it is judged apart, as "accel lateral".
"""

from __future__ import annotations

import math

import numpy as np

from guard.core.aiding.imu import lateral_rows
from guard.model.events import Notice
from guard.model.sensors import Sensor

TAU_S = 300.0           # s, the memory of the mean (exponential forgetting)
MATURE_S = 120.0        # s of a sensor's innovations before its fit is judged
WARN_FACTOR = 1.5       # innovations this many times the model's standard deviation
CLIP = 5.0
REPEAT_S = 600.0
REPEAT_GROWTH = 1.25
LATERAL = "accel lateral"   # the sideways constraint's channel of a ground vehicle's accelerometer test


class ModelFit:
    def __init__(self):
        self.acc: dict[str, list] = {}          # sensor -> [decayed sum of z^2, decayed count, first t, last t]
        self.said: dict[str, tuple[int, float]] = {}       # when a warning went out, and its factor

    def add(self, sensor: Sensor, t_us: int, r: np.ndarray, S: np.ndarray) -> None:
        """One fused innovation (python floats: this runs at every fusion)."""
        own, lateral = lateral_rows(sensor, len(r))
        r, var = r.tolist(), S.diagonal().tolist()
        self._add(sensor, t_us, r[own], var[own])
        if lateral is not None:
            self._add(LATERAL, t_us, r[lateral], var[lateral])

    def _add(self, sensor: str, t_us: int, r: list[float], var: list[float]) -> None:
        """r and its variances S_ii, of one sensor's rows."""
        z2 = 0.0
        for ri, si in zip(r, var):
            z2 += min(ri * ri / si, CLIP * CLIP)
        a = self.acc.get(sensor)
        if a is None:
            self.acc[sensor] = [z2, float(len(r)), t_us, t_us]
            return
        if t_us < a[3]:     # a new time base (a reboot): the mean carries over, its age with it (no exp overflow)
            a[2] -= a[3] - t_us
            a[3] = t_us
        decay = math.exp((a[3] - t_us) / (TAU_S * 1e6))
        a[0] = a[0] * decay + z2
        a[1] = a[1] * decay + len(r)
        a[3] = t_us

    def factor(self, sensor: str) -> float | None:
        """sqrt(mean z^2): 1 when the model fits; None before MATURE_S of innovations."""
        a = self.acc.get(sensor)
        if a is None or a[3] - a[2] < MATURE_S * 1e6:
            return None
        return math.sqrt(a[0] / a[1])

    def check(self, t_us: int) -> list[Notice]:
        out = []
        for sensor in self.acc:
            f = self.factor(sensor)
            if f is None or f < WARN_FACTOR:
                continue
            when, said = self.said.get(sensor, (None, 0.0))
            if when is not None and f < said * REPEAT_GROWTH and t_us - when < REPEAT_S * 1e6:
                continue
            self.said[sensor] = (t_us, f)
            out.append(Notice(t_us, "warning", f"{sensor} innovations {f:.1f}x the model: run guard tune"))
        return out
