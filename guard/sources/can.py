"""CAN source: GNSS and IMU samples read straight off a CAN bus as DroneCAN broadcasts.

URL `can:INTERFACE:CHANNEL` names a python-can interface and channel (`can:socketcan:can0`,
`can:virtual:bus0`, `can:udp_multicast:239.74.163.2`). python-can and dronecan are imported when a
`CanSource` is made, never at import time (importing dronecan parses all its DSDL, ~0.4 s).

Decoding uses dronecan's transport layer (`Frame`, `TransferManager`, `Transfer.from_frames`) fed by
a small bridge from python-can messages; dronecan's own python-can driver is not used.

Read: `uavcan.equipment.gnss.Fix2` (1063) from the GNSS node, `uavcan.equipment.ahrs.RawIMU` (1003)
and `uavcan.equipment.ahrs.MagneticFieldStrength2` (1002, gauss) from the IMU node. Each magnetometer
reading rides on the first ImuSample after it, and on no other (a slower compass is one measurement
per reading, not one per IMU sample).

Time stamps (`time_source`):
- "message" (default): t_us is `timestamp.usec` of Fix2 and of RawIMU, the bus's shared time base,
  so both sensors share one clock. Fix2's `gnss_timestamp` (UTC/GPS/TAI) is not used. A transfer
  whose `timestamp.usec` is 0 (UNKNOWN) is skipped and counted as `no_timestamp`.
- "receive": t_us is the python-can reception time of the transfer's first frame. Needed for
  ArduPilot's AP_Periph, which leaves RawIMU.timestamp at 0 and, once it had a fix, puts UTC epoch
  time in Fix2.timestamp.

`stats` counts, per reason, what was read and not turned into a sample (once per transfer):
unknown_type (a data type guard does not read, a service or anonymous transfer), other_node,
other_sensor (a second magnetometer on the IMU node), bad_transfer (wrong CRC, toggle or tail bits,
cut off, out of order, undecodable payload), no_timestamp, not_dronecan (11-bit, remote, error or
empty frames), silent (one per silence: a sensor's node sent nothing decodable for timeout_s),
gnss_bad_position (a 3D fix off the globe) and bad_value (an IMU or magnetometer value not finite or
beyond any sensor's range, a time stamp past 2100: the transfer is dropped; a GNSS velocity beyond
600 m/s: the fix is kept without it). A GNSS velocity that is not finite is left out of the fix.
`no_fix` counts Fix2 without a 3D fix; those are still yielded, with fix_ok=False, for the core.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator

from guard.errors import ConfigError, SourceError
from guard.model.samples import GnssFix, ImuSample

log = logging.getLogger(__name__)

FIX2, RAW_IMU, MAG2 = 1063, 1003, 1002          # DroneCAN data type ids
ROLE = {FIX2: "gnss", RAW_IMU: "imu", MAG2: "imu"}
REASONS = ("unknown_type", "other_node", "other_sensor", "bad_transfer", "no_fix", "no_timestamp",
           "not_dronecan", "silent", "gnss_bad_position", "bad_value")
T_MAX_US = 4_102_444_800_000_000        # 2100-01-01 in unix microseconds: no bus time goes past it
ACC_MAX_MPS2, GYRO_MAX_RADPS = 2000.0, 200.0    # beyond any MEMS range: corrupt data
MAG_MAX_GAUSS, SPEED_MAX_MPS = 10.0, 600.0      # beyond a magnetometer's range, a receiver's export limit


def parse_can_url(url: str) -> tuple[str, str]:
    """`can:INTERFACE:CHANNEL` -> (interface, channel). The channel may itself hold colons."""
    scheme, _, rest = url.partition(":")
    interface, _, channel = rest.partition(":")
    if scheme != "can" or not interface or not channel:
        raise ConfigError(f"bad CAN URL {url!r}: expected can:INTERFACE:CHANNEL, e.g. can:socketcan:can0")
    return interface, channel


def _node_id(name: str, value: int | None) -> int | None:
    if value is not None and not (isinstance(value, int) and 1 <= value <= 127):
        raise ConfigError(f"{name} must be a DroneCAN node id 1..127 or None, not {value!r}")
    return value


class CanSource:
    """Blocking source of GnssFix / ImuSample from one CAN bus.

    A node id of None means: lock onto the first node heard sending that sensor's messages.
    """

    def __init__(self, url: str, *, gnss_node_id: int | None, imu_node_id: int | None,
                 bus_kwargs: dict | None = None, timeout_s: float = 1.0, time_source: str = "message"):
        self.interface, self.channel = parse_can_url(url)
        self.name = f"{self.interface}:{self.channel}"
        if not timeout_s > 0:
            raise ConfigError(f"timeout_s must be > 0, not {timeout_s!r}")
        if time_source not in ("message", "receive"):
            raise ConfigError(f"time_source must be 'message' or 'receive', not {time_source!r}")
        self.timeout_s = float(timeout_s)
        self.time_source = time_source
        self.node = {"gnss": _node_id("gnss_node_id", gnss_node_id), "imu": _node_id("imu_node_id", imu_node_id)}
        self.stats: dict[str, int] = dict.fromkeys(REASONS, 0)
        self.messages: dict[str, int] = {}      # decoded transfers per DroneCAN type name
        self.stop = False
        self._mag: tuple[float, float, float] | None = None
        self._mag_sensor_id: int | None = None
        self._no_time_warned: set[int] = set()
        now = time.monotonic()
        self._last_heard = {"gnss": now, "imu": now}   # wall clock, for liveness only
        self._silent = {"gnss": False, "imu": False}

        import can                                     # lazily: only when a CAN source is configured
        from dronecan import transport

        self._can_errors = (can.CanError, OSError)
        self._transport = transport
        self._transfers = transport.TransferManager()
        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, **(bus_kwargs or {}))
        except Exception as exc:  # python-can raises many types (OSError, CanError, ValueError, ImportError)
            raise SourceError(f"cannot open CAN bus {self.name}: {exc}") from exc

    def __enter__(self) -> CanSource:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Stop `samples()` (within timeout_s) and release the bus. Safe from another thread."""
        self.stop = True
        self._bus.shutdown()

    def samples(self) -> Iterator[GnssFix | ImuSample]:
        """Yield samples until `close()` or `stop`; checks the flag at least every timeout_s."""
        while not self.stop:
            sample = self.poll(self.timeout_s)
            if sample is not None:
                yield sample

    def poll(self, timeout: float) -> GnssFix | ImuSample | None:
        """Wait up to `timeout` s for one frame; return the sample it completes, if any."""
        try:
            msg = self._bus.recv(timeout=timeout)
        except self._can_errors as exc:
            if self.stop:
                return None
            raise SourceError(f"cannot read CAN bus {self.name}: {exc}") from exc
        sample = self._on_message(msg) if msg is not None else None
        now = time.monotonic()
        pending = self._transfers.active_transfer_timestamps
        self._drop_transfers([k for k, t in pending.items() if now - t >= self.timeout_s])
        self._watch_silence(now)
        return sample

    # --- frames to transfers (the bridge) ---

    def _on_message(self, msg) -> GnssFix | ImuSample | None:
        if not msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or not msg.data:
            self.stats["not_dronecan"] += 1
            return None
        frame = self._transport.Frame(msg.arbitration_id, msg.data, ts_real=msg.timestamp, canfd=msg.is_fd)
        reason = self._reject(msg.arbitration_id)
        if reason is not None:
            if frame.start_of_transfer:
                self.stats[reason] += 1
            return None
        active = self._transfers.active_transfers
        if frame.start_of_transfer:
            # A sender emits one transfer of a type at a time: another one still pending was cut off.
            stale = [k for k in active if k[0] == frame.message_id]
            self._drop_transfers(stale)
        elif frame.transfer_key not in active:
            # dronecan drops a frame that continues no transfer silently; count it once, at its end.
            if frame.end_of_transfer:
                self.stats["bad_transfer"] += 1
            return None
        frames = self._transfers.receive_frame(frame)
        if frames is None:
            return None
        transfer = self._transport.Transfer()
        try:
            transfer.from_frames(frames)
        except (self._transport.TransferError, ValueError, IndexError) as exc:
            log.debug("CAN %s: bad transfer from id %#x: %s", self.name, msg.arbitration_id, exc)
            self.stats["bad_transfer"] += 1
            return None
        return self._on_transfer(transfer)

    def _reject(self, can_id: int) -> str | None:
        """Why a frame with this 29-bit id is not read, or None. Locks an unset node id."""
        source, dtid = can_id & 0x7F, (can_id >> 8) & 0xFFFF
        if can_id & 0x80 or source == 0 or dtid not in ROLE:     # service, anonymous, unused type
            return "unknown_type"
        role = ROLE[dtid]
        if self.node[role] is None:
            self.node[role] = source
            log.info("CAN %s: reading %s from node %d", self.name, role.upper(), source)
        return None if source == self.node[role] else "other_node"

    def _drop_transfers(self, keys: list) -> None:
        """Count pending transfers as cut off and forget them.

        Not dronecan's TransferManager.remove_inactive_transfers(): it raises RuntimeError (deletes
        from the dict it iterates over) as soon as there is something to remove.
        """
        for key in keys:
            del self._transfers.active_transfers[key]
            del self._transfers.active_transfer_timestamps[key]
            self.stats["bad_transfer"] += 1

    # --- transfers to samples (units converted here, once) ---

    def _on_transfer(self, transfer) -> GnssFix | ImuSample | None:
        m, dtid = transfer.payload, transfer.data_type_id
        type_name = self._transport.get_dronecan_data_type(m).full_name
        self.messages[type_name] = self.messages.get(type_name, 0) + 1
        if dtid == MAG2:
            if self._mag_sensor_id is None:
                self._mag_sensor_id = m.sensor_id
            mag = tuple(float(v) for v in m.magnetic_field_ga)
            if m.sensor_id != self._mag_sensor_id:
                self.stats["other_sensor"] += 1
            elif not _within(mag, MAG_MAX_GAUSS):
                self.stats["bad_value"] += 1
            else:
                self._mag = mag
            return None
        self._heard(ROLE[dtid])
        t_us = self._t_us(m.timestamp.usec, transfer, type_name)
        if t_us is None:
            return None
        if dtid == RAW_IMU:
            ax, ay, az = acc = tuple(m.accelerometer_latest)
            gx, gy, gz = gyro = tuple(m.rate_gyro_latest)
            if not (_within(acc, ACC_MAX_MPS2) and _within(gyro, GYRO_MAX_RADPS)):
                self.stats["bad_value"] += 1
                return None
            mx, my, mz = self._mag if self._mag is not None else (None, None, None)
            self._mag = None            # one reading, one measurement: on the first IMU sample after it only
            return ImuSample(t_us, ax, ay, az, gx, gy, gz, mx, my, mz)
        fix_ok = m.status >= 3                      # STATUS_3D_FIX
        lat, lon = m.latitude_deg_1e8 / 1e8, m.longitude_deg_1e8 / 1e8
        if fix_ok and not (abs(lat) <= 90 and abs(lon) <= 180 and (lat, lon) != (0.0, 0.0)):
            self.stats["gnss_bad_position"] += 1
            return None
        if not fix_ok:
            self.stats["no_fix"] += 1               # still yielded: the core announces the loss
        h_acc, vel_acc = _accuracies(list(m.covariance))
        vn, ve, _vd = m.ned_velocity
        if not (math.isfinite(vn) and math.isfinite(ve)):
            vn = ve = None
        elif not _within((vn, ve), SPEED_MAX_MPS):
            self.stats["bad_value"] += 1
            vn = ve = None
        return GnssFix(t_us=t_us, fix_ok=fix_ok, lat_deg=lat, lon_deg=lon, alt_m=m.height_msl_mm / 1000.0,
                       vel_n_mps=vn, vel_e_mps=ve, h_acc_m=h_acc, vel_acc_mps=vel_acc)

    def _t_us(self, usec: int, transfer, type_name: str) -> int | None:
        if self.time_source == "receive":
            return round(transfer.ts_real * 1e6)
        if usec == 0:                              # uavcan.Timestamp.UNKNOWN
            self.stats["no_timestamp"] += 1
            if transfer.data_type_id not in self._no_time_warned:
                self._no_time_warned.add(transfer.data_type_id)
                log.warning("CAN %s: %s from node %d has no timestamp (0); skipped. "
                            "Use time_source='receive' for such nodes", self.name, type_name,
                            transfer.source_node_id)
            return None
        if usec > T_MAX_US:
            self.stats["bad_value"] += 1
            return None
        return usec

    # --- liveness (wall clock, never used as a sample time) ---

    def _heard(self, role: str) -> None:
        now = time.monotonic()
        if self._silent[role]:
            self._silent[role] = False
            log.info("CAN %s: %s from node %s again after %.1f s", self.name, role.upper(),
                     self.node[role], now - self._last_heard[role])
        self._last_heard[role] = now

    def _watch_silence(self, now: float) -> None:
        for role, last in self._last_heard.items():
            if not self._silent[role] and now - last >= self.timeout_s:
                self._silent[role] = True
                self.stats["silent"] += 1
                node = "any node" if self.node[role] is None else f"node {self.node[role]}"
                log.warning("CAN %s: no %s from %s for %.1f s; still waiting", self.name,
                            role.upper(), node, now - last)


def _within(values, limit: float) -> bool:
    """Every value finite and at most `limit` in size."""
    return all(abs(v) <= limit for v in values)       # False for NaN


def _accuracies(cov: list[float]) -> tuple[float | None, float | None]:
    """Fix2 covariance (1, 6 diagonal or 36 full; m^2 and (m/s)^2) -> (h_acc_m, vel_acc_mps), 1 sigma."""
    if len(cov) == 1:
        var = cov * 6
    elif len(cov) == 6:
        var = cov
    elif len(cov) == 36:
        var = cov[::7]
    else:
        return None, None

    def sigma(a: float, b: float) -> float | None:
        ok = all(math.isfinite(v) and v >= 0 for v in (a, b))   # NaN: the sender does not know
        return math.sqrt(max(a, b)) if ok else None

    return sigma(var[0], var[1]), sigma(var[3], var[4])
