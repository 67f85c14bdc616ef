"""pyulog's reading of a ULog file: the topics guard uses, and where pyulog stopped short.

The file is read once, into memory, and its framing walked (guard.sources.ulog.framing): where
corrupt bytes broke it, pyulog reads the file without the spans that could not be framed, so that
it does not lose the messages after them. pyulog reads the whole file at once and prints what it
finds wrong on stdout: that is caught and logged (the first lines as warnings, the rest counted). It stops silently at a cut message; the
file it reads notices (its last read came up short) and says where.
"""

from __future__ import annotations

import io
import logging

from pyulog import ULog
from pyulog.exceptions import ULogException

from guard.errors import SourceError
from guard.sources.ulog.framing import Walk, mend
from guard.sources.logs_common import printed

log = logging.getLogger(__name__)

MAGIC = b"ULog\x01\x12\x35"
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")
TOPICS = [*GPS_TOPICS, "sensor_combined", "vehicle_imu", "vehicle_magnetometer", "vehicle_attitude",
          "vehicle_status", "estimator_innovation_test_ratios", "estimator_status"]


def looks_like_ulog(head: bytes) -> bool:
    """A ULog file starts with "ULog", 0x01 0x12 0x35 (then its version and start time)."""
    return head[:7] == MAGIC


class _TrackedFile:
    """The file as pyulog reads it. `cut_at`: where its last read began if that read came up short
    (pyulog stops there silently: a file cut inside a message, or corrupt bytes read as a long one). An
    empty read of a 3-byte message header is the file's end, not a cut.

    pyulog steps back after a message it reads as corrupt by the size it asked for, not the size it
    got: after a short read, at the end of the file, that lands before the message and it reads the
    same bytes again, for ever. A step back is taken from where the bytes asked for would have ended."""

    def __init__(self, f):
        self._f, self.cut_at = f, None
        self._short = 0         # bytes the last read came up short by

    def read(self, n: int = -1) -> bytes:
        at = self._f.tell()
        data = self._f.read(n)
        self._short = max(n - len(data), 0)
        if data or n not in (-1, 3):        # nothing for a message's body: the file ends after its header
            self.cut_at = at if 0 <= n and len(data) < n else None
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        if whence == 1 and offset < 0:
            offset = min(offset + self._short, 0)
        self._short = 0
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def close(self) -> None:
        """pyulog closes its file when done; the reader closes its own."""


def _mended(f, path: str) -> tuple[io.BytesIO, bool, Walk]:
    """The file's bytes for pyulog, without the spans its framing's walk skipped; whether it skipped
    any; and the walk. The file is read whole, once (a read error is a SourceError, where a mapped
    file's would kill the process); its definitions' formats, as pyulog reads them, give the walk its
    topics' sizes."""
    try:
        data = f.read()
    except OSError as e:
        raise SourceError(f"{path}: cannot read: {e.strerror}") from None
    try:
        formats = ULog(_TrackedFile(io.BytesIO(data)), parse_header_only=True).message_formats
    except Exception:       # noqa: BLE001 - definitions pyulog cannot read: the walk learns the sizes
        formats = None
    mended, walk = mend(data, formats)
    return io.BytesIO(data if mended is None else mended), mended is not None, walk


def load(path: str, topics: list[str] | None = None) -> tuple[ULog, int | None, Walk]:
    """pyulog's reading of the topics guard uses (or of `topics`), the offset where it stopped short
    (None: at the end), and the walk."""
    try:
        f = open(path, "rb")
    except OSError as e:
        raise SourceError(f"{path}: cannot open: {e.strerror}") from None
    with f, printed() as said:
        data, mended, walk = _mended(f, path)
        tracked = _TrackedFile(data)
        try:
            ulog = ULog(tracked, message_name_filter_list=TOPICS if topics is None else topics)
        except ULogException as e:
            raise SourceError(f"{path}: not a ULog file guard can read ({e})") from None
        except OSError as e:
            raise SourceError(f"{path}: cannot read: {e.strerror}") from None
        except Exception as e:      # noqa: BLE001 - pyulog parses untrusted bytes: anything it raises means unreadable
            raise SourceError(f"{path}: cannot be read as ULog ({type(e).__name__}: {e})") from None
    for line in said.first:
        log.warning("%s: pyulog: %s", path, line)
    if said.lines > len(said.first):
        log.warning("%s: pyulog: %d more lines like these", path, said.lines - len(said.first))
    cut_at = walk.in_file(tracked.cut_at) if tracked.cut_at is not None and mended else tracked.cut_at
    return ulog, cut_at, walk
