"""What the autopilot-log readers (`guard.sources.dataflash`, `guard.sources.ulog`) share.

- The autopilot's verdicts, one record shape for both formats: an episode of an EKF innovation test
  ratio above 1.0 (`ratio_episodes`; times in microseconds since the autopilot booted, the log's own
  time base) and a text message the autopilot wrote about GNSS (`message_verdict`).
- What a parsing library prints (pymavlink's DFReader, pyulog) caught instead of reaching stdout,
  where it would corrupt `guard replay --report -` (`printed`).
- When a magnetometer reading is fresh enough to ride on an IMU sample (`mag_fresh`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np

MAG_FRESH_US = 500_000          # a magnetometer reading older than this is not attached to an IMU sample
KEEP_LINES = 5                  # what a library prints: the first lines kept for the log, the rest counted


def mag_fresh(t_us, mag_t_us):
    """Whether a magnetometer reading at `mag_t_us` is close enough to time `t_us` (us) to attach it
    to the IMU sample of that time; scalars or numpy arrays alike."""
    return abs(t_us - mag_t_us) < MAG_FRESH_US


def ratio_episodes(t: np.ndarray, ratio: np.ndarray, source: str, test: str, *, gap_us: int | None = None,
                   digits: int = 3) -> list[dict]:
    """One verdict per episode of an innovation test ratio above 1.0 (the measurement failed its gate):
    its first and last time (us) and its peak, rounded to `digits`.

    `t`, `ratio`: the test's records in log order; a non-finite ratio is not above 1. An episode is a
    run of consecutive records above 1 (`gap_us` None) or, with `gap_us`, of records above 1 whose
    times are at most `gap_us` apart (the records at or below 1 between them do not end it).
    """
    ratio = np.asarray(ratio, dtype=np.float64)
    at = np.flatnonzero(np.isfinite(ratio) & (ratio > 1.0))        # the records above 1
    if not at.size:
        return []
    t = np.asarray(t)
    breaks = np.diff(at) > 1 if gap_us is None else np.diff(t[at]) > gap_us
    starts = np.r_[0, np.flatnonzero(breaks) + 1]
    ends = np.r_[starts[1:], at.size]
    peaks = np.maximum.reduceat(ratio[at], starts)
    return [{"time_usec": int(t[at[a]]), "end_usec": int(t[at[b - 1]]), "source": source, "test": test,
             "peak_ratio": round(float(peak), digits)} for a, b, peak in zip(starts, ends, peaks)]


def message_verdict(t_us: int, text: str, level: str | None = None) -> dict:
    """A text message of the autopilot's (about GNSS), as a verdict; `level` where the log says it."""
    out = {"time_usec": int(t_us), "source": "autopilot", "test": "message"}
    if level is not None:
        out["level"] = level
    out["text"] = text
    return out


class Printed:
    """A file-like sink for what a library prints: counts its non-blank lines and keeps the first
    KEEP_LINES of them (without their line ends), however the text is cut into writes."""

    def __init__(self) -> None:
        self.lines = 0
        self.first: list[str] = []
        self._part = ""             # the last line, until its end is written

    def write(self, text: str) -> int:
        lines = (self._part + text).splitlines(keepends=True)
        self._part = lines.pop() if lines and lines[-1].splitlines()[0] == lines[-1] else ""
        for line in lines:
            self._line(line.splitlines()[0])
        return len(text)

    def flush(self) -> None:
        """Nothing buffered for a reader: a line without its end is taken when printing stops."""

    def end(self) -> None:
        """Take the last line, if it was written without an end."""
        if self._part:
            self._line(self._part)
            self._part = ""

    def _line(self, line: str) -> None:
        if line.strip():
            self.lines += 1
            if len(self.first) < KEEP_LINES:
                self.first.append(line)


@contextlib.contextmanager
def printed(stderr: bool = False) -> Iterator[Printed]:
    """Catch what is printed on stdout (and stderr if asked) inside the block, in a `Printed`."""
    said = Printed()
    try:
        with contextlib.redirect_stdout(said), \
                contextlib.redirect_stderr(said) if stderr else contextlib.nullcontext():
            yield said
    finally:
        said.end()
