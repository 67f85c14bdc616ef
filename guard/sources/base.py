"""What every log source gives replay: samples in stream order, and an account of what it read.

A reader opens its file in its constructor (a `SourceError` naming the file if it cannot), yields
samples from `samples()`, and counts as it goes: `messages` per type seen, `skipped` per reason,
`position` of `size` bytes for a progress bar. `date` is the day the log was recorded (the magnetic
declination depends on it; None when the log does not say); `utc_offset_us`, where the log gives UTC
(GPS time, the ground station's time prefix), what turns its time stamps into UTC (t_us + it), for
logs written in the flight's own time (`guard.sinks.mcap`). `notes` are lines for the user about
what the log holds and guard does not use (a second IMU, a receiver it did not pick). `verdicts` are
the autopilot's own findings, where the log holds them (EKF innovations' test ratios, GPS glitches).
Live links (`guard.sources.link`, `guard.sources.can`) poll instead of iterating a file.
"""

from __future__ import annotations

import datetime
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Iterator

from guard.model.samples import Sample


class LogSource(ABC):
    path: str
    size: int = 0
    position: int = 0
    date: datetime.date | None = None
    utc_offset_us: int | None = None      # t_us + it = UTC microseconds (None: unknown)
    first_time_us: int | None = None      # the log's first and last time stamps (its duration)
    last_time_us: int | None = None

    def __init__(self) -> None:
        self.messages: Counter[str] = Counter()
        self.skipped: Counter[str] = Counter()
        self.notes: list[str] = []
        self.verdicts: list[dict] = []

    @abstractmethod
    def samples(self) -> Iterator[Sample]:
        """The samples of the log in stream order."""

    def close(self) -> None:
        """Release the file."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
