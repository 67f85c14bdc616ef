"""An ArduPilot DataFlash log written as the tlog a ground station would have recorded of the same
flight: each IMU, GPS and attitude sample at its own rate, as MAVLink RAW_IMU (carrying the latest
compass reading, as an autopilot streams it), GPS_RAW_INT and ATTITUDE, with a HEARTBEAT a second.
With --px4 (and a PX4 ULog too), as PX4's onboard link sends it instead: the IMU as HIGHRES_IMU at
50 Hz, its latest sample each 20 ms (PX4's stream sends the latest integrated IMU sample, it does
not average), the magnetometer marked new (fields_updated) when a reading came since the last.

    python tools/dataflash_to_tlog.py FLIGHT.bin OUT.tlog
    python tools/dataflash_to_tlog.py FOLDER OUT_FOLDER        # every .bin in FOLDER
    python tools/dataflash_to_tlog.py --px4 FOLDER OUT_FOLDER  # every .bin and .ulg, as PX4 sends it

The time stamps are the autopilot's, as logged: a DataFlash log whose clock parts from the GNSS time
is put right by guard's DataFlash reader, which a tlog, whose GPS_RAW_INT carries no GNSS time,
cannot be in the same way (guard.sources.clock checks it against the receiver's motion instead).
This is how guard is tried on telemetry of real flights that were only logged on board; the tlog's
prefix is the flight's UTC where the log says it.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as mavlink     # noqa: E402

from guard.errors import GuardError                  # noqa: E402
from guard.model.samples import Attitude, GnssFix, ImuSample, VehicleType    # noqa: E402
from guard.sources.dataflash import DataFlashReader  # noqa: E402
from guard.sources.mavlink import HIGHRES_ACC_GYRO, HIGHRES_MAG     # noqa: E402
from guard.sources.ulog import UlogReader            # noqa: E402

G = 9.80665
UNKNOWN_U16 = 65535
NO_UTC_US = 1_600_000_000_000_000       # the prefix's origin for a log that does not say its UTC
PX4_IMU_US = 20_000                     # PX4's onboard link: HIGHRES_IMU at 50 Hz


class Frames:
    """pymavlink's output, caught frame by frame."""

    def __init__(self):
        self.buf = bytearray()

    def write(self, data: bytes) -> None:
        self.buf += data


def i16(v: float) -> int:
    return max(-32767, min(32767, round(v)))


def convert(src: str, dst: str, px4: bool = False) -> int:
    """Write `src` as a tlog at `dst` (as PX4's onboard link sends it, with px4); the frames written."""
    ulog = src.lower().endswith(".ulg")
    reader = UlogReader(src) if ulog else DataFlashReader(src, as_logged=True)
    frames = Frames()
    mav = mavlink.MAVLink(frames, srcSystem=1, srcComponent=1)
    ground = getattr(reader, "ground", False)
    kind = mavlink.MAV_TYPE_GROUND_ROVER if ground else mavlink.MAV_TYPE_QUADROTOR
    autopilot = mavlink.MAV_AUTOPILOT_PX4 if px4 else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    mag, last_heartbeat, n = (0, 0, 0), None, 0
    last_imu, mag_si, mag_new = None, (0.0, 0.0, 0.0), False
    try:
        with open(dst, "wb") as out:
            def emit(t_us: int, msg) -> None:
                nonlocal n
                frames.buf = bytearray()
                mav.send(msg)
                prefix = (reader.utc_offset_us or NO_UTC_US) + t_us
                out.write(prefix.to_bytes(8, "big") + bytes(frames.buf))
                n += 1

            for s in reader.samples():
                if isinstance(s, VehicleType):      # the log's vehicle, before its first sample (a ULog's too)
                    kind = mavlink.MAV_TYPE_GROUND_ROVER if s.ground else mavlink.MAV_TYPE_QUADROTOR
                t = getattr(s, "t_us", None)
                if t is None:
                    continue
                if last_heartbeat is None or t - last_heartbeat >= 1_000_000:
                    emit(t, mavlink.MAVLink_heartbeat_message(kind, autopilot, 0, 0, 0, 3))
                    last_heartbeat = t
                if isinstance(s, ImuSample) and px4:
                    if s.mag_x_gauss is not None:
                        mag_si, mag_new = (s.mag_x_gauss, s.mag_y_gauss, s.mag_z_gauss), True
                    if last_imu is not None and 0 <= t - last_imu < PX4_IMU_US - 2_500:   # half a 200 Hz sample
                        continue
                    last_imu = t
                    emit(t, mavlink.MAVLink_highres_imu_message(
                        t, s.acc_x_mps2, s.acc_y_mps2, s.acc_z_mps2, s.gyro_x_radps, s.gyro_y_radps, s.gyro_z_radps,
                        *mag_si, 0.0, 0.0, 0.0, 0.0, HIGHRES_ACC_GYRO | (HIGHRES_MAG if mag_new else 0)))
                    mag_new = False
                elif isinstance(s, ImuSample):
                    if s.mag_x_gauss is not None:
                        mag = (i16(s.mag_x_gauss * 1000), i16(s.mag_y_gauss * 1000), i16(s.mag_z_gauss * 1000))
                    emit(t, mavlink.MAVLink_raw_imu_message(
                        t, i16(s.acc_x_mps2 * 1000 / G), i16(s.acc_y_mps2 * 1000 / G), i16(s.acc_z_mps2 * 1000 / G),
                        i16(s.gyro_x_radps * 1000), i16(s.gyro_y_radps * 1000), i16(s.gyro_z_radps * 1000), *mag))
                elif isinstance(s, GnssFix):
                    vel = cog = UNKNOWN_U16
                    if s.vel_n_mps is not None:
                        vel = round(math.hypot(s.vel_n_mps, s.vel_e_mps) * 100)
                        cog = round(math.degrees(math.atan2(s.vel_e_mps, s.vel_n_mps)) % 360 * 100) % 36000
                    emit(t, mavlink.MAVLink_gps_raw_int_message(
                        t, 3 if s.fix_ok else 1, round(s.lat_deg * 1e7), round(s.lon_deg * 1e7), round(s.alt_m * 1000),
                        round(s.hdop * 100) if s.hdop else UNKNOWN_U16, UNKNOWN_U16, vel, cog, 10,
                        h_acc=round((s.h_acc_m or 0) * 1000), vel_acc=round((s.vel_acc_mps or 0) * 1000)))
                elif isinstance(s, Attitude):
                    emit(t, mavlink.MAVLink_attitude_message(t // 1000, s.roll_rad, s.pitch_rad, 0.0, 0.0, 0.0, 0.0))
    finally:
        reader.close()
    return n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", help="a DataFlash log (or with --px4 a ULog), or a folder of them")
    ap.add_argument("dst", help="the tlog to write, or a folder for them")
    ap.add_argument("--px4", action="store_true", help="as PX4's onboard link sends it: HIGHRES_IMU at 50 Hz")
    args = ap.parse_args(argv)
    src, dst = Path(args.src), Path(args.dst)
    kinds = {".bin", ".ulg"} if args.px4 else {".bin"}
    if src.is_dir():
        dst.mkdir(parents=True, exist_ok=True)
        jobs = [(p, dst / (p.stem + ".tlog")) for p in sorted(src.iterdir()) if p.suffix.lower() in kinds]
    elif src.exists():
        jobs = [(src, dst)]
    else:
        print(f"guard: {src}: no such file or folder", file=sys.stderr)
        return 2
    for a, b in jobs:
        try:
            n = convert(str(a), str(b), args.px4)
        except (GuardError, OSError) as e:
            print(f"guard: {a}: {e}", file=sys.stderr)
            return 1
        print(f"{a.name} -> {b}: {n} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
