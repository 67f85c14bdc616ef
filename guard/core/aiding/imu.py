"""IMU aiding: the magnetometer's heading, the gyro's yaw rate and the accelerometer's horizontal
specific force, fused as one stacked measurement and tested sensor by sensor.

    z = (theta_mag, omega_z, a_x, a_y[, 0])    h(x) = H x
    H rows: theta;  theta_dot + b_theta_dot;  a_x + b_ax;  a_y + b_ay;  [ground vehicles: v_y = 0]
A tilted IMU (a flying drone) is first levelled with the autopilot's roll and pitch, and a fast IMU
averaged down to `imu_fusion_hz` (as PX4's EKF2 does): the mean of the samples since the last fusion
is fused at the last one's time, which keeps a 250 Hz IMU affordable on a companion computer.
"""

from __future__ import annotations

import math

import numpy as np

from guard.core.aiding import Aid
from guard.core.ekf import AX, AY, BAX, BAY, BW, N_STATES, TH, VY, W, FilterConfig
from guard.model.samples import ImuSample
from guard.model.sensors import Sensor

# IMU block: heading, gyro, accel x, accel y
H_IMU = np.zeros((4, N_STATES))
H_IMU[0, TH] = 1.0
H_IMU[1, W] = H_IMU[1, BW] = 1.0
H_IMU[2, AX] = H_IMU[2, BAX] = 1.0
H_IMU[3, AY] = H_IMU[3, BAY] = 1.0
H_IMU_NO_MAG = H_IMU[1:]
# ground vehicles: the same with the sideways velocity v_y = 0 appended
H_LATERAL = np.zeros((1, N_STATES)); H_LATERAL[0, VY] = 1.0
H_IMU_GROUND, H_IMU_NO_MAG_GROUND = np.vstack([H_IMU, H_LATERAL]), np.vstack([H_IMU_NO_MAG, H_LATERAL])
# rows of the stacked IMU measurement that belong to each sensor: (sensor, first, last + 1)
IMU_BLOCKS = ((Sensor.MAG, 0, 1), (Sensor.GYRO, 1, 2), (Sensor.ACCEL, 2, 4))
IMU_BLOCKS_NO_MAG = ((Sensor.GYRO, 0, 1), (Sensor.ACCEL, 1, 3))


def level(s: ImuSample, phi: float, p: float):
    """Horizontal specific force (forward, left), ENU yaw rate and the levelled field (m_x, m_y).

    The body axes are FRD; a tilted IMU is rotated to the local level frame with the latest
    roll phi and pitch p: v_level = R_y(p) R_x(phi) v_body.
    """
    if phi == 0.0 and p == 0.0:
        fx, fy = s.acc_x_mps2, s.acc_y_mps2
        yaw_rate_ned = s.gyro_z_radps
        mx, my = s.mag_x_gauss, s.mag_y_gauss
    else:
        cr, sr, cp, sp = math.cos(phi), math.sin(phi), math.cos(p), math.sin(p)
        fx = cp * s.acc_x_mps2 + sp * sr * s.acc_y_mps2 + sp * cr * s.acc_z_mps2
        fy = cr * s.acc_y_mps2 - sr * s.acc_z_mps2
        yaw_rate_ned = (sr * s.gyro_y_radps + cr * s.gyro_z_radps) / cp
        if s.mag_x_gauss is not None:
            mx = cp * s.mag_x_gauss + sp * sr * s.mag_y_gauss + sp * cr * s.mag_z_gauss
            my = cr * s.mag_y_gauss - sr * s.mag_z_gauss
        else:
            mx = my = None
    mag = (mx, my) if mx is not None and math.hypot(mx, my) > 1e-3 else None
    return fx, -fy, -yaw_rate_ned, mag


def heading(mx: float, my: float, declination: float) -> float:
    """ENU yaw from the levelled field: compass chi = atan2(-m_y, m_x) + declination, theta = pi/2 - chi."""
    return math.remainder(math.pi / 2 - (math.atan2(-my, mx) + declination), math.tau)


class Averager:
    """The mean of the IMU samples since the last fusion, due every 1/imu_fusion_hz (0: every sample)."""

    def __init__(self, fusion_hz: float):
        self.fusion_hz = fusion_hz
        self.t_us: int | None = None            # time of the last fused IMU measurement
        self._clear()

    def _clear(self) -> None:
        self.sum = [0.0] * 5                    # ax, ay, yaw rate, m_x, m_y since the last fusion
        self.n = self.mag_n = 0

    def add(self, t_us: int, ax: float, ay: float, rate: float, mag) -> tuple | None:
        """Add a sample; when a fusion is due, (ax, ay, rate, mag) averaged, else None."""
        acc = self.sum
        acc[0] += ax; acc[1] += ay; acc[2] += rate
        self.n += 1
        if mag is not None:
            acc[3] += mag[0]; acc[4] += mag[1]
            self.mag_n += 1
        hz = self.fusion_hz
        if hz > 0 and self.t_us is not None and t_us - self.t_us < 0.9e6 / hz:
            return None
        n, nm = self.n, self.mag_n
        out = acc[0] / n, acc[1] / n, acc[2] / n, (acc[3] / nm, acc[4] / nm) if nm else None
        self._clear()
        self.t_us = t_us
        return out


class ImuAiding:
    """Builds the stacked IMU measurement and the rows each sensor owns."""

    def __init__(self, f: FilterConfig):
        self.f = f
        sig = [f.heading_sigma_rad, f.gyro_sigma_radps, f.accel_sigma_mps2, f.accel_sigma_mps2, f.lateral_sigma_mps]
        # indexed by `ground`: the IMU block, and for a ground vehicle the sideways velocity after it
        self.R = (np.diag(np.square(sig[:4])), np.diag(np.square(sig)))
        self.R_no_mag = (self.R[0][1:, 1:].copy(), self.R[1][1:, 1:].copy())
        self.H = (H_IMU, H_IMU_GROUND)
        self.H_no_mag = (H_IMU_NO_MAG, H_IMU_NO_MAG_GROUND)

    def measurement(self, x: np.ndarray, theta: float | None, rate: float, ax: float, ay: float, ground: bool):
        """(Aid, blocks, angle_rows) of one fusion; theta None without a magnetometer."""
        if theta is None:
            z, H, R, blocks = [rate, ax, ay], self.H_no_mag[ground], self.R_no_mag[ground], IMU_BLOCKS_NO_MAG
        else:
            z, H, R, blocks = [theta, rate, ax, ay], self.H[ground], self.R[ground].copy(), IMU_BLOCKS
            # a heading sampled up to heading_lag_s late is off by up to yaw rate * lag
            R[0, 0] += (rate * self.f.heading_lag_s) ** 2
        if ground:
            z.append(0.0)                          # the sideways velocity of a wheeled vehicle
        angle = (0,) if theta is not None else ()
        return Aid(np.array(z), H @ x, H, R), blocks, angle
