"""Whether an air vehicle has a compass at all.

An air vehicle whose IMU has spoken for NO_COMPASS_S without a magnetometer reading (none fitted, or
one that reads all zeros) has no heading reference: hovering, nothing observes its heading, which
then wanders with the gyro, and every acceleration integrated along a wrong heading is a velocity
error the GNSS contradicts (real copters without a compass: 7 to 33 false alarms a flight). Its IMU
is then not integrated, as a slow one is not: GNSS position and velocity are tested against each
other alone. A ground vehicle keeps its IMU: its sideways constraint makes the GNSS course witness
the heading. A magnetometer that speaks later (one that started late) gives the heading back, and
so does the autopilot's word that the vehicle is on wheels, if it comes after the IMU was set aside.

This file decides; the monitor acts (guard.core.monitor: holds the heading, or starts the filter
again inertial).
"""

from __future__ import annotations

NO_COMPASS_S = 10.0     # s of IMU samples without a magnetometer reading: an air vehicle has no compass


class CompassWatch:
    def __init__(self):
        self.t0: int | None = None      # the IMU stream's first sample
        self.heard = False              # a magnetometer reading has come with some sample since
        self.absent = False             # the IMU was set aside for want of one

    def check(self, t_us: int, heard: bool, ground: bool, inertial: bool | None) -> str | None:
        """Per IMU sample: "absent" once an inertial air vehicle's IMU has spoken NO_COMPASS_S without a
        magnetometer reading; "back" at the first reading after that, "ground" if the vehicle turns out
        to be on wheels (the autopilot's word came late); None otherwise (every sample once a
        magnetometer has spoken)."""
        if self.absent and (heard or ground):
            self.absent = False
            self.heard = heard
            return "back" if heard else "ground"
        self.heard |= heard
        if self.heard:
            return None
        if self.t0 is None:
            self.t0 = t_us
        if ground or inertial is not True or t_us - self.t0 < NO_COMPASS_S * 1e6:
            return None
        self.absent = True
        return "absent"
