"""The attitude that levels the IMU, at each IMU sample's own time.

The autopilot's roll and pitch (ATTITUDE, DataFlash ATT, ULog vehicle_attitude) come at 4 to 50 Hz,
sampled apart from the IMU. Held until the next one, a 10 Hz attitude is on average 50 ms old; a
copter rolling at 1 rad/s is then levelled with a tilt 3 degrees out, and gravity leaks
g x 0.05 rad = 0.5 m/s^2 into the horizontal specific force, in one direction for the whole
manoeuvre: a velocity error the GNSS contradicts. Each IMU sample therefore carries the latest
attitude forward to its own time with its own gyro (the Euler angles' kinematics):

    phi_dot   = p + (q sin phi + r cos phi) tan theta
    theta_dot = q cos phi - r sin phi

for at most MAX_CARRY_S after the attitude (the gyro's bias, 0.01 rad/s, adds 1 mrad in 0.1 s);
past that, or near a vertical pitch, the attitude is held as it came.
"""

from __future__ import annotations

import math

from guard.model.samples import Attitude, ImuSample

MAX_CARRY_S = 0.5       # s: the longest an attitude is carried forward by the gyro
MAX_PITCH_RAD = 1.4     # tan(pitch) beyond this (80 degrees) is not integrated


class Tilt:
    """Roll and pitch (rad) at the time of each IMU sample."""

    def __init__(self):
        self.roll = self.pitch = 0.0
        self.t_att: int | None = None           # the autopilot's latest attitude, and how far it has been
        self.t_us: int | None = None            # carried (the last IMU sample's time)

    def set(self, a: Attitude) -> None:
        self.roll, self.pitch = a.roll_rad, a.pitch_rad
        self.t_att = self.t_us = a.t_us

    def at(self, s: ImuSample) -> tuple[float, float]:
        """(roll, pitch) at s.t_us: the latest attitude carried forward with the gyro."""
        if self.t_us is None or s.t_us <= self.t_us or s.t_us - self.t_att > MAX_CARRY_S * 1e6 \
                or abs(self.pitch) > MAX_PITCH_RAD:
            return self.roll, self.pitch
        dt = (s.t_us - self.t_us) / 1e6
        phi, theta = self.roll, self.pitch
        p, q, r = s.gyro_x_radps, s.gyro_y_radps, s.gyro_z_radps
        sp, cp = math.sin(phi), math.cos(phi)
        self.roll = phi + dt * (p + (q * sp + r * cp) * math.tan(theta))
        self.pitch = theta + dt * (q * cp - r * sp)
        self.t_us = s.t_us
        return self.roll, self.pitch
