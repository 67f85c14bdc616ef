"""The autopilot's roll and pitch carried to each IMU sample's time by the gyro (guard.core.aiding.tilt)."""

import math

import pytest

from guard.core.aiding.tilt import MAX_CARRY_S, Tilt
from guard.model.samples import Attitude, ImuSample


def imu(t_us, p=0.0, q=0.0, r=0.0):
    return ImuSample(t_us, 0.0, 0.0, -9.8, p, q, r, None, None, None)


def test_a_roll_rate_is_integrated_from_the_latest_attitude():
    tilt = Tilt()
    tilt.set(Attitude(1_000_000, 0.1, 0.0))
    for k in range(1, 6):                                   # 0.1 s at 1 rad/s of roll rate, 50 Hz
        roll, pitch = tilt.at(imu(1_000_000 + 20_000 * k, p=1.0))
    assert roll == pytest.approx(0.2) and pitch == pytest.approx(0.0)
    tilt.set(Attitude(1_100_000, 0.25, 0.05))               # the autopilot's word replaces the carried one
    assert tilt.at(imu(1_100_000)) == (0.25, 0.05)


def test_a_yaw_rate_in_a_tilted_body_turns_roll_and_pitch_as_the_euler_kinematics_say():
    """Rolled 30 degrees, a body yaw rate r pitches the vehicle at -r sin(phi) and rolls it at
    r cos(phi) tan(theta)."""
    tilt = Tilt()
    phi, theta = math.radians(30.0), math.radians(10.0)
    tilt.set(Attitude(0, phi, theta))
    roll, pitch = tilt.at(imu(10_000, r=0.5))
    assert pitch - theta == pytest.approx(-0.01 * 0.5 * math.sin(phi))
    assert roll - phi == pytest.approx(0.01 * 0.5 * math.cos(phi) * math.tan(theta))


def test_an_attitude_too_old_or_ahead_of_the_imu_is_held_as_it_came():
    tilt = Tilt()
    assert tilt.at(imu(1_000_000, p=1.0)) == (0.0, 0.0)                      # no attitude yet: level
    tilt.set(Attitude(2_000_000, 0.1, 0.2))
    assert tilt.at(imu(1_990_000, p=1.0)) == (0.1, 0.2)                      # an IMU sample older than it
    late = 2_000_000 + int(MAX_CARRY_S * 1e6) + 20_000
    assert tilt.at(imu(late, p=1.0)) == (0.1, 0.2)                           # past MAX_CARRY_S: held
