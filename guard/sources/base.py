"""What every log source gives replay: samples in stream order, and an account of what it read.

A reader opens its file in its constructor (a `SourceError` naming the file if it cannot), yields
samples from `samples()`, and counts as it goes: `messages` per type seen, `skipped` per reason,
`position` of `size` bytes for a progress bar. `date` is the day the log was recorded (the magnetic
declination depends on it; None when the log does not say); `utc_offset_us`, where the log gives UTC
(GPS time, the ground station's time prefix), what turns its time stamps into UTC (t_us + it), for
logs written in the flight's own time (`guard.sinks.mcap`). `notes` are lines for the user about
what the log holds and guard does not use (a second IMU, a receiver it did not pick). `verdicts` are
the autopilot's own findings, where the log holds them (EKF innovations' test ratios, GPS glitches),
on the samples' clock. `clock`, where the autopilot's clock did not keep time against its GNSS
receiver's (guard.sources.clock), is (t0, rate): every time stamp t of the log was put at
t0 + (t - t0) rate; `as_logged` takes a sample's time back to the log's own (its other records').
Live links (`guard.sources.link`, `guard.sources.can`) poll instead of iterating a file.
"""

from __future__ import annotations

import datetime
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Iterator

from guard.model.samples import Sample


def as_logged(t_us: int, clock: tuple[int, float] | None) -> int:
    """A time on the samples' clock (an alarm's) back on the log's own, where its other records are:
    `clock` is the source's (a report's `clock`: t0_usec, rate)."""
    if clock is None:
        return t_us
    t0, rate = clock
    return t0 + round((t_us - t0) / rate)


class LogSource(ABC):
    path: str
    size: int = 0
    position: int = 0
    date: datetime.date | None = None
    utc_offset_us: int | None = None      # t_us + it = UTC microseconds (None: unknown)
    first_time_us: int | None = None      # the log's first and last time stamps (its duration)
    last_time_us: int | None = None
    clock: tuple[int, float] | None = None    # (t0, rate): the log's time stamps rescaled; None: as logged

    def __init__(self) -> None:
        self.messages: Counter[str] = Counter()
        self.skipped: Counter[str] = Counter()
        self.notes: list[str] = []
        self.verdicts: list[dict] = []

    @abstractmethod
    def samples(self) -> Iterator[Sample]:
        """The samples of the log in stream order."""

    def on_clock(self, t_us: int) -> int:
        """A time stamp of the log on the samples' clock."""
        if self.clock is None:
            return t_us
        t0, rate = self.clock
        return t0 + round((t_us - t0) * rate)

    def _verdicts_on_clock(self) -> None:
        """The autopilot's verdicts, read with the log's own time stamps, put on the samples' clock."""
        self.verdicts = [{k: self.on_clock(v) if k in ("time_usec", "end_usec") else v for k, v in verdict.items()}
                         for verdict in self.verdicts]

    def close(self) -> None:
        """Release the file."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
