"""Events: what the core hands the sinks (MCAP log, STATUSTEXT, replay report, plots).

The core's step takes one sample and returns a list of these. Sinks never look inside the filter:
they see innovations, test statistics, alarms and the estimate, nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymap3d

from guard.model.sensors import AMBIGUOUS, CHANNELS, UNITS, Sensor   # noqa: F401 (re-exported for sinks)


@dataclass(frozen=True, slots=True)
class Innovation:
    """One fusion of one sensor (PX4's record): r = y - ŷ and its covariance S = H P Hᵀ + R.

    `r` has shape (m,), `S` shape (m, m), in the units of CHANNELS. `fused` is False when the
    measurement was tested but not fused (sensor excluded while judged attacked). `modelled` is False
    where the measurement's error is not the sensor's modelled noise and its variance was widened for
    it (a course the receiver held at low speed, whose error repeats fix after fix): the model's fit,
    the wander and `guard tune` leave it out.
    """

    t_us: int
    sensor: Sensor
    channels: tuple[str, ...]
    r: np.ndarray
    S: np.ndarray
    fused: bool
    modelled: bool = True


@dataclass(frozen=True, slots=True)
class Tested:
    """An innovation with the detector's statistic and threshold, one per channel."""

    __test__ = False    # not a pytest test class, whatever its name

    innovation: Innovation
    gnss_index: int
    statistic: tuple[float, ...]
    threshold: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class Alarm:
    """The detector rejected H0 on one channel: an attack (or fault) is declared at t_us.

    `offset` is the detector's estimate of the shift, in the channel's units (metres for GNSS
    position): it is what a ground station shows as the size of the attack. `ambiguous_with` names
    the other sensors that would leave the same trace (see AMBIGUOUS): the alarm does not guess.
    `standing`: the sensor's earlier alarm still stands (it was re-anchored on without its ever
    agreeing again) and came within guard.core.judge.STANDING_GAP_S: this one says the disagreement
    goes on, not that a new one began (a ramp on a GNSS tested alone alarms again after each
    re-anchoring).
    """

    t_us: int
    gnss_index: int
    sensor: Sensor
    channel: str
    statistic: float
    threshold: float
    offset: float
    detector: str
    ambiguous_with: tuple[Sensor, ...] = ()
    standing: bool = False


@dataclass(frozen=True, slots=True)
class Cleared:
    """A sensor that raised an alarm agrees with the others again."""

    t_us: int
    gnss_index: int
    sensor: str
    channel: str


@dataclass(frozen=True, slots=True)
class Notice:
    """A status line for the operator: GNSS lost or back, filter re-initialised, and the like."""

    t_us: int
    level: str      # "info" | "warning"
    text: str


@dataclass(frozen=True, slots=True)
class Estimate:
    """The navigation estimate after a GNSS sample: position, heading, speed and covariance diagonal."""

    t_us: int
    gnss_index: int
    east_m: float
    north_m: float
    yaw_rad: float          # ENU yaw: 0 = east, counter-clockwise positive
    x: np.ndarray           # the full state, shape (N_STATES,) (guard.core.ekf: 14)
    P_diag: np.ndarray      # its covariance's diagonal, the same shape
    origin: tuple[float, float, float]   # lat_deg, lon_deg, alt_m of the local frame's origin
    fix_en: tuple[float, float] | None = None   # the fix's own east, north (m): how far the estimate is from it
    fix_fused: bool = True  # whether the fix's position was fused (False: excluded by an alarm, the estimate
                            # held by the other sensors: its distance from the fix is that exclusion's)

    def lat_lon(self) -> tuple[float, float]:
        """The estimated position in WGS-84 degrees (computed on demand: it costs ~0.1 ms)."""
        lat, lon, _ = pymap3d.enu2geodetic(self.east_m, self.north_m, 0.0, *self.origin)
        return float(lat), float(lon)


Event = Tested | Alarm | Cleared | Notice | Estimate
