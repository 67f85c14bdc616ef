"""Which sensors are excluded, since when, and how they come back.

A sensor whose test rejects H0 raises an Alarm and is then excluded: its innovations are still
formed and tested, but no longer fused, so the estimate rides on the other sensors instead of
following the attack. It is re-admitted (Cleared) when its normalised innovations have stayed
within `readmit_sigma` for `readmit_s` seconds and READMIT_SAMPLES samples, and its witnesses no
longer hold it (the monitor says so: `settle(..., bad=...)`). GNSS position and velocity come from
one receiver and go together; a sensor excluded with the receiver, not by an alarm of its own,
comes back without a Cleared (a ground station has nothing to clear).
"""

from __future__ import annotations

from collections import Counter

from guard.model.events import Cleared, Event
from guard.model.sensors import CHANNELS, RECEIVER, Sensor

READMIT_SAMPLES = 10   # and at least this many samples in a row (a 1 Hz receiver: 10 s, not 3 samples)


class Health:
    def __init__(self, receiver: tuple[Sensor, ...], readmit_s: float):
        self.receiver = receiver                    # what one receiver's alarm excludes
        self.readmit_s = readmit_s
        self.excluded: dict[Sensor, int] = {}       # sensor -> time of the last inconsistent innovation
        self.agreed: Counter[Sensor] = Counter()    # excluded sensor -> consistent samples since then
        self.with_receiver: set[Sensor] = set()     # excluded with the receiver, not by an alarm of its own
        self.accel_ref: float | None = None         # a laterally biased accelerometer's bias before the attack
        self.lateral = False                        # the accelerometer's "lateral" channel is tested (on wheels)
        self.latched: set[Sensor] = set()           # fused again without being cleared (re-anchored): the alarm stands
        self.offsets: dict[Sensor, float] = {}      # the size of each excluded sensor's alarm (its estimated shift)

    def exclude(self, named: Sensor, t_us: int, offset: float | None = None) -> None:
        """An alarm on `named` (of size `offset`, if known): it goes, and with a GNSS sensor the rest of
        its receiver (a spoofer controls both; the one that still agrees is re-admitted after readmit_s)."""
        if offset is not None and named in RECEIVER:
            self.size(named, offset)
        for out in self.receiver if named in RECEIVER else (named,):
            if out not in self.excluded and out != named:
                self.with_receiver.add(out)
            self.excluded[out] = t_us
            self.agreed.pop(out, None)
        self.with_receiver.discard(named)

    def size(self, sensor: Sensor, offset: float | None) -> None:
        """From now until it is re-admitted, the excluded `sensor`'s agreeing counts only where its test
        could see its alarm's `offset` (`blind`); an offset not known (None) is taken as 0, which no
        test can see: the sensor then waits to be re-anchored on."""
        self.offsets[sensor] = abs(offset) if offset is not None else 0.0

    def blind(self, sensor: Sensor, sigma: float, readmit_sigma: float) -> bool:
        """Could a test whose innovation has standard deviation `sigma` not tell the alarm's offset
        from noise? Then agreeing with it proves nothing: the estimate has drifted too far to judge
        (the sensor waits; an estimate that cannot hold is re-anchored, its alarm standing). For the
        GNSS, whose test is against the estimate, and for a compass whose alarm left the gyro a suspect
        (the judge sizes it, and judges it on the heading's own uncertainty); the IMU's wait on their
        witnesses."""
        return readmit_sigma * sigma >= self.offsets.get(sensor, float("inf"))

    def settle(self, sensor: Sensor, t_us: int, bad: bool) -> bool:
        """One more test of an excluded sensor; True when it is to be re-admitted now."""
        agreed = self.agreed.pop(sensor, 0)     # samples in a row that agreed; a bad one resets it
        if bad:
            self.excluded[sensor] = t_us        # still inconsistent
            return False
        if t_us - self.excluded[sensor] < self.readmit_s * 1e6 or agreed + 1 < READMIT_SAMPLES:
            self.agreed[sensor] = agreed + 1
            return False
        return True

    def readmit(self, sensor: Sensor, t_us: int, gnss_index: int, silent: bool = False) -> list[Event]:
        """Fuse `sensor` again. `silent`: not because it agreed (the estimate was re-anchored on it):
        its alarm stands, latched, and no Cleared goes out."""
        del self.excluded[sensor]
        self.agreed.pop(sensor, None)
        self.offsets.pop(sensor, None)
        if sensor == Sensor.ACCEL:
            self.accel_ref = None
        if sensor in self.with_receiver:            # it raised no alarm: nothing to clear on a ground station
            self.with_receiver.discard(sensor)
            return []
        if silent:
            self.latched.add(sensor)
            return []
        self.latched.discard(sensor)
        return [Cleared(t_us, gnss_index, sensor, c) for c in self.channels(sensor)]

    def channels(self, sensor: Sensor) -> tuple[str, ...]:
        """The channels a sensor's test has: the accelerometer's "lateral" on wheels only."""
        return CHANNELS[sensor] if self.lateral else tuple(c for c in CHANNELS[sensor] if c != "lateral")

    def alarmed(self) -> set[Sensor]:
        """The sensors whose alarm stands: excluded by an alarm of their own, or latched."""
        return {s for s in self.excluded if s not in self.with_receiver} | self.latched

    def carried(self, t_us: int, gnss_index: int) -> tuple[list[Event], set[Sensor]]:
        """Across a re-initialisation (a new filter fuses every sensor again): the alarms cleared, but
        a GNSS alarm's, which stands (a new filter starts on the GNSS: nothing has shown the attack over).
        Returns the Cleared events and the sensors whose alarm is carried over, latched."""
        gone = self.alarmed()
        kept = gone & set(RECEIVER)
        return [Cleared(t_us, gnss_index, s, c) for s in sorted(gone - kept) for c in self.channels(s)], kept
