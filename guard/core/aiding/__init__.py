"""Aiding sources: one file per sensor group, as PX4's EKF2 keeps one file per aid source.

Each builds its measurement for the filter: z, h(x), H and R, in one `Aid` record; the monitor forms
the innovation r = z - h(x) and S = H P Hᵀ + R from it, tests r against S, and fuses it or not.
Deciding *whether* to fuse is the monitor's and `guard.core.health`'s; the math is here and in
`guard.core.ekf`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Aid(NamedTuple):
    """One measurement for the filter: z (m,), h(x) (m,), H (m, n), R (m, m); `axis`, where one direction
    only is measured (a unit vector u, r along it): each channel is tested against u^T S u, S's
    variance along it, not against its own diagonal of S, which holds what is not measured too."""

    z: np.ndarray
    hx: np.ndarray
    H: np.ndarray
    R: np.ndarray
    axis: np.ndarray | None = None

    def tested(self, S: np.ndarray) -> np.ndarray:
        """The covariance the innovation is tested against: S, or along `axis` on every channel."""
        if self.axis is None:
            return S
        return float(self.axis @ S @ self.axis) * np.eye(len(self.z))
