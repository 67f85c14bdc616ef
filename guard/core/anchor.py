"""Where the filter starts, and where it starts again: the first state from a fix, a diverged filter
told apart, and an estimate re-anchored on the GNSS when the other sensors can no longer hold it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from guard.core.ekf import BM, KS, LA, N_STATES, TH, VX, VY, X, Y, NavEKF, body_velocity
from guard.model.samples import GnssFix

MAX_POS_SIGMA_M = 10_000.0     # an estimate less sure of its position than this has diverged
MAX_SPEED_MPS = 300.0          # nor does a vehicle guard watches move faster


def initial_state(fix: GnssFix, theta_mag: float | None, b0: float, k0: float = 0.0, d0: float = 0.0) -> np.ndarray:
    """The first state: at the fix's position (the frame's origin), the heading the magnetometer
    reads less its known offset b0 (else the course, when moving, else 0), the fix's velocity, the
    wheels' known slip k0 and the sensors' known place ahead of the axle d0."""
    x0 = np.zeros(N_STATES)
    x0[KS], x0[LA] = k0, d0
    ve, vn = fix.vel_e_mps or 0.0, fix.vel_n_mps or 0.0
    x0[BM] = b0                                 # the compass reads theta + b_psi
    if theta_mag is not None:
        th = math.remainder(theta_mag - b0, math.tau)
    else:
        th = math.atan2(vn, ve) if math.hypot(ve, vn) > 1.0 else 0.0
    x0[TH] = th
    x0[VX], x0[VY] = body_velocity(th, ve, vn)
    return x0


@dataclass(frozen=True)
class Learnt:
    """What a filter learnt of the vehicle, not of the moment: the compass's offset b_psi, the
    wheels' slip k_s and the sensors' place ahead of the axle d, with their variances. A filter
    started again on the same vehicle (a reboot) starts from them."""

    b_psi: float
    var_b_psi: float
    k_s: float
    var_k_s: float
    d: float = 0.0
    var_d: float = 0.0

    @classmethod
    def of(cls, ekf: NavEKF) -> Learnt | None:
        """None where the filter learnt nothing: on GNSS alone (NavEKF.hold_heading) both are held at
        nothing, and a new filter had better learn them afresh than start certain of nothing."""
        x, P = ekf.x, ekf.P
        if P[BM, BM] <= 0.0 and P[KS, KS] <= 0.0:
            return None
        return cls(float(x[BM]), float(P[BM, BM]), float(x[KS]), float(P[KS, KS]), float(x[LA]), float(P[LA, LA]))

    def restore(self, ekf: NavEKF) -> None:
        """Their variances into a new filter (whose x0 already holds their values), uncorrelated."""
        ekf.P[BM, :] = ekf.P[:, BM] = 0.0
        ekf.P[KS, :] = ekf.P[:, KS] = 0.0
        ekf.P[LA, :] = ekf.P[:, LA] = 0.0
        ekf.P[BM, BM], ekf.P[KS, KS], ekf.P[LA, LA] = self.var_b_psi, self.var_k_s, self.var_d

    def __str__(self) -> str:
        return (f"compass offset b_psi {math.degrees(self.b_psi):+.1f} deg "
                f"(+-{math.degrees(math.sqrt(self.var_b_psi)):.1f}), wheel slip k_s {self.k_s:.4f}, "
                f"sensors {self.d:+.2f} m ahead of the axle")


def diverged(ekf: NavEKF) -> str | None:
    """Why the filter cannot be trusted any more (None: it can): not finite, a negative variance,
    lost in position or at a speed no vehicle here reaches."""
    x, P = ekf.x, ekf.P
    if not (np.isfinite(x).all() and np.isfinite(P).all()):
        return "its state is not finite"
    if np.diagonal(P).min() < 0.0:
        return "a negative variance"
    if P[X, X] + P[Y, Y] > MAX_POS_SIGMA_M ** 2 or abs(x[VX]) > MAX_SPEED_MPS or abs(x[VY]) > MAX_SPEED_MPS:
        return "lost in position or speed"
    return None


def anchor(ekf: NavEKF, fix: GnssFix, en: tuple[float, float], sigma_pos: float, sigma_vel: float,
           late_s: float = 0.0) -> None:
    """The estimate's position (and velocity, where the fix has one) set to the fix's, uncorrelated,
    with the fix's own noise as their uncertainty. A fix from a receiver late_s late (gnss_delay_s)
    shows where the vehicle was then: its position is carried to now by its velocity, else the next
    late fix finds the estimate that far behind (a fix without a velocity is taken as it is: the
    estimate's own velocity is what could not be held)."""
    x, P = ekf.x, ekf.P
    ve, vn = (fix.vel_e_mps, fix.vel_n_mps) if fix.vel_n_mps is not None else (0.0, 0.0)
    x[X], x[Y] = en[0] + ve * late_s, en[1] + vn * late_s
    anchored = [X, Y]
    if fix.vel_n_mps is not None:
        x[VX], x[VY] = body_velocity(x[TH], fix.vel_e_mps, fix.vel_n_mps)
        anchored += [VX, VY]
    P[anchored, :] = 0.0
    P[:, anchored] = 0.0
    P[X, X] = P[Y, Y] = sigma_pos ** 2
    if fix.vel_n_mps is not None:
        P[VX, VX] = P[VY, VY] = sigma_vel ** 2
