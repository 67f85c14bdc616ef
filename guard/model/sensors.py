"""The sensors guard tests, their channels and units, and what the physics cannot tell apart.

A sensor is named by `Sensor` everywhere (a `str` enum: it prints, compares and serialises as its
value, "gnss_pos"). Adding a sensor is one member here, its channels and unit, and one aiding file
in `guard.core.aiding`.
"""

from __future__ import annotations

from enum import StrEnum


class Sensor(StrEnum):
    GNSS_POS = "gnss_pos"      # GNSS position, east and north (m)
    GNSS_VEL = "gnss_vel"      # GNSS velocity, east and north (m/s)
    MAG = "mag"                # heading from the magnetometer (rad)
    GYRO = "gyro"              # yaw rate (rad/s)
    ACCEL = "accel"            # horizontal specific force, x forward and y left (m/s^2); on wheels, and
                               # "lateral": the sideways velocity it builds against them (m/s)


CHANNELS: dict[Sensor, tuple[str, ...]] = {
    Sensor.GNSS_POS: ("east", "north"),
    Sensor.GNSS_VEL: ("east", "north"),
    Sensor.MAG: ("yaw",),
    Sensor.GYRO: ("z",),
    Sensor.ACCEL: ("x", "y", "lateral"),     # "lateral": a ground vehicle's only (its innovation has 3 rows)
}
UNITS: dict[Sensor, str] = {Sensor.GNSS_POS: "m", Sensor.GNSS_VEL: "m/s", Sensor.MAG: "rad", Sensor.GYRO: "rad/s",
                            Sensor.ACCEL: "m/s^2"}

# In the paper's model the yaw rate and the accelerations are random-walk states that follow the
# IMU, so an IMU bias surfaces in the sensor it contradicts: a gyro bias in the magnetometer's
# heading, an accelerometer bias in the GNSS velocity. An alarm there names both (measured with
# tools/eval.py: family "imu").
AMBIGUOUS: dict[Sensor, tuple[Sensor, ...]] = {Sensor.MAG: (Sensor.GYRO,), Sensor.GNSS_VEL: (Sensor.ACCEL,)}

# the sensors of one receiver: a spoofer controls them all, an alarm on one excludes them together
RECEIVER: tuple[Sensor, ...] = (Sensor.GNSS_POS, Sensor.GNSS_VEL)
