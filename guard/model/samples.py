"""Samples: what a source hands the core, in SI units with integer microsecond time stamps.

Units are converted once, at the edge where a MAVLink or CAN message is read (`guard.sources.mavlink`,
`guard.sources.can`). Nothing after that knows a wire format. Time stamps come from the message
(`time_usec`, the DroneCAN timestamp), never from the wall clock, so replay, live and a sped-up
simulator behave the same.

Body axes are the autopilot's: x forward, y right, z down (FRD). Specific force is what an
accelerometer measures: about -9.81 m/s^2 on z when level and at rest.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class GnssFix:
    """One GNSS solution (GPS_RAW_INT, DroneCAN Fix2)."""

    t_us: int
    fix_ok: bool             # a 3D fix (fix_type >= 3); when False the position fields mean nothing
    lat_deg: float
    lon_deg: float
    alt_m: float
    vel_n_mps: float | None  # ground velocity, north (None when the receiver sends none)
    vel_e_mps: float | None  # ground velocity, east
    h_acc_m: float | None    # receiver's horizontal accuracy estimate, when it sends one
    vel_acc_mps: float | None
    hdop: float | None = None   # horizontal dilution of precision, where the receiver gives one (a receiver
                                # that reports no accuracy still reports its geometry)


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One IMU sample (RAW_IMU, HIGHRES_IMU, DroneCAN RawIMU + magnetometer), body frame FRD."""

    t_us: int
    acc_x_mps2: float        # specific force
    acc_y_mps2: float
    acc_z_mps2: float
    gyro_x_radps: float
    gyro_y_radps: float
    gyro_z_radps: float
    mag_x_gauss: float | None   # None when the message carries no magnetometer reading
    mag_y_gauss: float | None
    mag_z_gauss: float | None


@dataclass(frozen=True, slots=True)
class Attitude:
    """The autopilot's roll and pitch (ATTITUDE), used only to level a tilted IMU (a flying drone)."""

    t_us: int
    roll_rad: float
    pitch_rad: float


@dataclass(frozen=True, slots=True)
class VehicleType:
    """The autopilot's vehicle class (HEARTBEAT.type): a ground rover cannot slide sideways."""

    ground: bool


Sample = GnssFix | ImuSample | Attitude | VehicleType
