"""How far a sensor's innovations wander: the long-run scale of each test.

A CUSUM's threshold (Siegmund's) holds for innovations that are white: z = r / sqrt(S) independent
from sample to sample. Real sensors' errors are not. A multicopter's compass carries the motors'
field and the tilt's coupling, a few degrees that come and go over seconds; a receiver's velocity
error lasts seconds, its position error minutes. Each sample may be well inside its model (real
logs: z of 0.2 to 0.8 rms against the model's 1) while its mean over a second wanders at 0.5 to 1:
a CUSUM sums that wander and, at k = 0.5, alarms within two seconds of it (real copters: mag,
gnss_vel and gyro alarms at 1.0 to 1.5 of their threshold, minutes apart, with nothing wrong).

The scale F of a channel is the standard deviation of its innovations' block means over the white
model's: F^2 = N mean(zbar^2) for blocks of N = BLOCK samples (1 for white noise of unit variance;
less, for a model too generous per sample). BLOCK is the small-shift member's window, about h / k
samples (h near 20, k = 0.5), which is the time scale on which a wander reaches the CUSUM. The
test then sees r against S F^2, as a CUSUM on data whose long-run variance is F^2 keeps its
false-alarm budget, and an attack is caught against the wander the vehicle has, not against none:
later, by F, on a vehicle that wanders, as any test on that vehicle would be.

F adapts as the compass offset does: slowly (the mean forgets over TAU_S), within bounds
(1 <= F <= F_MAX: never more sensitive than the model, never blind), and only while every test is
calm (Judge.calm): a slow attack pushes some statistic up long before its alarm, and while it does
F learns nothing from it, so it cannot widen the test it is being caught by. A fix whose variance
was widened past the model (a held course: Innovation.modelled) is left out as a test not calm is:
the block being filled is dropped. It starts at 1 (the
model as configured) and takes a few blocks to learn: an alarm in the first seconds of a wandering
sensor is still possible. Above WARN_F the model does not fit: said once per sensor, as a WARNING
naming the factor (the fix is `guard tune`, or a noise model for that vehicle).
"""

from __future__ import annotations

import math

import numpy as np

from guard.model.events import Notice
from guard.model.sensors import Sensor

BLOCK = 40              # samples per block mean (the small-shift member's window)
TAU_S = 300.0           # s, the memory of the mean square of the block means
PRIOR_BLOCKS = 2.0      # the model's own F = 1 counts as this many blocks until the memory is full
F_MAX = 4.0             # the widest a test is made
WARN_F = 1.5            # a wander this many times the model's is said
CLIP = 5.0              # one glitch counts for at most this many sigmas


def normalised(r: np.ndarray, S: np.ndarray) -> np.ndarray:
    """z = r / sqrt(S_ii), each clipped at CLIP."""
    return np.clip(r / np.sqrt(np.diagonal(S)), -CLIP, CLIP)


class BlockMeans:
    """A sensor's normalised innovations summed per channel over BLOCK samples: add() gives back the
    block's mean and how long it lasted (s) when it closes, else None (guard tune reads them too)."""

    def __init__(self):
        self.sum: np.ndarray | None = None
        self.n = 0
        self.t0 = 0

    def add(self, z: np.ndarray, t_us: int = 0) -> tuple[np.ndarray, float] | None:
        if self.sum is None or len(self.sum) != len(z):
            self.sum, self.n, self.t0 = np.zeros(len(z)), 0, t_us
        self.sum += z
        self.n += 1
        if self.n < BLOCK:
            return None
        zbar, duration = self.sum / self.n, max(0.0, (t_us - self.t0) / 1e6)
        self.sum = None
        return zbar, duration


class LongRun:
    def __init__(self, f_max: float = F_MAX):
        self.f_max = f_max
        self.blocks: dict[Sensor, BlockMeans] = {}
        self.v: dict[Sensor, np.ndarray] = {}    # sensor -> mean of N zbar^2 per channel
        self.n: dict[Sensor, float] = {}         # blocks taken
        self.said: set[Sensor] = set()

    def scale(self, sensor: Sensor, S: np.ndarray) -> np.ndarray:
        """S as the test sees it: F_i F_j S_ij."""
        v = self.v.get(sensor)
        if v is None or len(v) != len(S):       # its channels changed (a vehicle found on wheels): as the model says
            return S
        f = self.factors(sensor)
        return S * np.outer(f, f)

    def factors(self, sensor: Sensor) -> np.ndarray:
        v = self.v.get(sensor)
        if v is None:
            return np.ones(1)
        return np.clip(np.sqrt(v), 1.0, self.f_max)

    def add(self, sensor: Sensor, t_us: int, r: np.ndarray, S: np.ndarray) -> Notice | None:
        """One calm, fused innovation (against the model's own S, not the scaled one)."""
        closed = self.blocks.setdefault(sensor, BlockMeans()).add(normalised(r, S), t_us)
        if closed is None:
            return None
        zbar, duration = closed
        n = self.n.get(sensor, 0.0)
        v = self.v.get(sensor)
        if v is None or len(v) != len(zbar):
            v, n = np.ones(len(zbar)), 0.0
        # a running mean with the model as a prior, until it has TAU_S of blocks; then it forgets
        alpha = max(1.0 / (n + 1.0 + PRIOR_BLOCKS), 1.0 - math.exp(-duration / TAU_S))
        self.v[sensor] = v + alpha * (BLOCK * zbar * zbar - v)
        self.n[sensor] = n + 1.0
        f = float(self.factors(sensor).max())
        if f < WARN_F or sensor in self.said or n + 1.0 < 2 * PRIOR_BLOCKS:
            return None
        self.said.add(sensor)
        return Notice(t_us, "warning", f"{sensor} innovations wander {f:.1f}x what the model allows: its test "
                      "widened to match (run guard tune)")

    def interrupt(self, sensor: Sensor) -> None:
        """A test not calm, or the sensor excluded: the block being filled is dropped, not closed later
        with a gap in it."""
        self.blocks.pop(sensor, None)
