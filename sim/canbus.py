"""The vehicle's CAN side: publishes DroneCAN GNSS, IMU and magnetometer broadcasts on a CAN bus.

Like an ArduPilot AP_Periph node: `uavcan.equipment.gnss.Fix2` from the GNSS node,
`uavcan.equipment.ahrs.RawIMU` and `uavcan.equipment.ahrs.MagneticFieldStrength2` from the IMU
node. Encoding is dronecan's (`Transfer(...).to_frames()`); frames go out as python-can messages
with 29-bit ids. URL `can:INTERFACE:CHANNEL` as for python-can (`can:virtual:bus0`,
`can:socketcan:vcan0`). This module imports nothing from guard: it only talks through frames.
"""

from __future__ import annotations

import math

PRIORITY_HIGH, PRIORITY_LOW = 8, 24          # libcanard's levels; AP_Periph sends RawIMU high, Fix2 low


def parse_url(url: str) -> tuple[str, str]:
    """`can:INTERFACE:CHANNEL` -> (interface, channel)."""
    scheme, _, rest = url.partition(":")
    interface, _, channel = rest.partition(":")
    if scheme != "can" or not interface or not channel:
        raise ValueError(f"bad CAN URL {url!r}: expected can:INTERFACE:CHANNEL")
    return interface, channel


class CanPublisher:
    """Sends one DroneCAN transfer per call; keeps a transfer id per (data type, node)."""

    def __init__(self, url: str, *, gnss_node_id: int = 10, imu_node_id: int = 11,
                 bus_kwargs: dict | None = None):
        interface, channel = parse_url(url)
        import can                                  # lazily: only when CAN output is asked for
        import dronecan

        self._can, self._dronecan = can, dronecan
        self.gnss_node_id, self.imu_node_id = gnss_node_id, imu_node_id
        self._transfer_ids: dict[tuple[int, int], int] = {}
        try:
            self._bus = can.Bus(interface=interface, channel=channel, **(bus_kwargs or {}))
        except Exception as exc:  # python-can raises OSError, CanError, ValueError, ImportError
            raise OSError(f"cannot open CAN bus {interface}:{channel}: {exc}") from exc

    def __enter__(self) -> CanPublisher:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        self._bus.shutdown()

    # --- encode: one transfer -> its frames, as python-can messages (also for tampering in tests) ---

    def encode_gnss(self, t_us: int, lat_deg: float, lon_deg: float, alt_m: float, vel_n: float,
                    vel_e: float, vel_d: float, fix3d: bool, h_acc_m: float | None, *,
                    v_acc_m: float | None = None, vel_acc_mps: float | None = None, sats_used: int = 12):
        """Fix2. Accuracies (1 sigma) go out as a 6-element diagonal covariance, NaN when unknown.

        `gnss_timestamp` is left UNKNOWN (the simulator has no UTC); the simulator has no geoid, so
        the ellipsoid height is the MSL height.
        """
        m = self._dronecan.uavcan.equipment.gnss.Fix2()
        m.timestamp.usec = t_us
        m.latitude_deg_1e8 = round(lat_deg * 1e8)
        m.longitude_deg_1e8 = round(lon_deg * 1e8)
        m.height_msl_mm = m.height_ellipsoid_mm = round(alt_m * 1000.0)
        m.ned_velocity = [vel_n, vel_e, vel_d]
        m.status = 3 if fix3d else 0                    # STATUS_3D_FIX or STATUS_NO_FIX
        m.sats_used = sats_used if fix3d else 0
        if h_acc_m is not None:
            var = [_sq(h_acc_m), _sq(h_acc_m), _sq(v_acc_m)] + [_sq(vel_acc_mps)] * 3
            m.covariance = var
        return self._encode(m, self.gnss_node_id, PRIORITY_LOW)

    def encode_imu(self, t_us: int, acc_frd_mps2: tuple[float, float, float],
                   gyro_frd_radps: tuple[float, float, float]):
        """RawIMU: specific force (m/s^2) and rate (rad/s), body FRD, latest samples only (float16)."""
        m = self._dronecan.uavcan.equipment.ahrs.RawIMU()
        m.timestamp.usec = t_us
        m.integration_interval = 0.0                    # non-positive: no integrated samples
        m.accelerometer_latest = list(acc_frd_mps2)
        m.rate_gyro_latest = list(gyro_frd_radps)
        return self._encode(m, self.imu_node_id, PRIORITY_HIGH)

    def encode_mag(self, t_us: int, mag_frd_gauss: tuple[float, float, float], *, sensor_id: int = 0):
        """MagneticFieldStrength2 (gauss, body FRD, float16). The message has no time stamp field:
        `t_us` is accepted for symmetry and not sent; a receiver pairs it with the next RawIMU."""
        m = self._dronecan.uavcan.equipment.ahrs.MagneticFieldStrength2()
        m.sensor_id = sensor_id
        m.magnetic_field_ga = list(mag_frd_gauss)
        return self._encode(m, self.imu_node_id, PRIORITY_LOW)

    def _encode(self, payload, node_id: int, priority: int) -> list:
        dtid = self._dronecan.get_dronecan_data_type(payload).default_dtid
        tid = self._transfer_ids.get((dtid, node_id), 0)
        self._transfer_ids[(dtid, node_id)] = (tid + 1) % 32       # 5-bit transfer id
        transfer = self._dronecan.transport.Transfer(
            transfer_id=tid, source_node_id=node_id, payload=payload, transfer_priority=priority)
        return [self._can.Message(arbitration_id=f.message_id, is_extended_id=True, data=bytes(f.bytes))
                for f in transfer.to_frames()]

    # --- send ---

    def send(self, messages: list) -> None:
        for msg in messages:
            self._bus.send(msg)

    def send_gnss(self, t_us: int, lat_deg: float, lon_deg: float, alt_m: float, vel_n: float,
                  vel_e: float, vel_d: float, fix3d: bool, h_acc_m: float | None, **extra) -> None:
        self.send(self.encode_gnss(t_us, lat_deg, lon_deg, alt_m, vel_n, vel_e, vel_d, fix3d, h_acc_m, **extra))

    def send_imu(self, t_us: int, acc_frd_mps2: tuple[float, float, float],
                 gyro_frd_radps: tuple[float, float, float]) -> None:
        self.send(self.encode_imu(t_us, acc_frd_mps2, gyro_frd_radps))

    def send_mag(self, t_us: int, mag_frd_gauss: tuple[float, float, float], **extra) -> None:
        self.send(self.encode_mag(t_us, mag_frd_gauss, **extra))


def _sq(sigma: float | None) -> float:
    return math.nan if sigma is None else sigma * sigma
