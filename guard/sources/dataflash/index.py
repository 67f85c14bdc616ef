"""DFReader's index of a DataFlash log, and rows of chosen message types decoded from it.

How it is read: `DFReader_binary` frames the file, parses the FMT messages and indexes the offset
of every message per type. guard then decodes only the types it needs from that index, with the
struct formats and multipliers DFReader built from the FMT messages: DFMessage attribute access
runs at about 40 k messages/s, struct on the index at about 1 M/s. Three things are changed in
DFReader, by subclassing: its C fast indexer is replaced by its Python twin (pymavlink's current
`dfindexer.c` calls exit() on an undeclared type or an FMT of length < 3), an FMT declaring a
length below 3 is refused (DFReader frames by that length; 0 makes it loop forever:
`bad_format`), a header of a type no FMT declared is stepped past instead of ending the index
(`_Formats`), and its GPS clock, which guard does not use, is skipped (it parses the whole file
when a log has no GPS). DFReader prints what it skips: that is captured and logged at debug level.

Time: a row's first value is the message's boot time in microseconds: `TimeUS`, or older logs'
`TimeMS` (ms); their GPS has boot ms in `T` and GPS time of week in `TimeMS`/`Week`.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable, Iterator

from pymavlink import DFReader

from guard.errors import SourceError
from guard.sources.logs_common import printed

log = logging.getLogger(__name__)

HEAD = b"\xa3\x95"
FMT_TYPE = 0x80
MAX_BOOT_US = 10**13              # ~116 days: a larger boot time stamp is corrupt data


def looks_like_dataflash(head: bytes) -> bool:
    """A DataFlash log starts with a message header and an FMT message (type 128)."""
    return len(head) >= 5 and head[:3] == HEAD + bytes((FMT_TYPE,)) and head[4] >= 4


class _Formats(dict):
    """DFReader's table of formats, refusing an FMT whose length is shorter than a header: DFReader
    frames messages by that length, and a corrupt one of 0 makes its indexer loop forever. (A length
    that disagrees with the format is kept: ArduCopter 3.4 declares BAR3 4 bytes longer than its
    format, and its messages are framed by the length.)

    While the file is indexed (`indexing`), a type no FMT declared is taken as a bare header
    (UNDECLARED, 3 bytes long): DFReader's indexer stops at the first such header and reads nothing
    after it, so one corrupt type byte lost the rest of the log (88 % of a real Erle flight). Taken as
    3 bytes, the indexer steps past it and finds the next header, as it does after any garbage; its
    offsets stay under that type, which no FMT names, and are counted as `undeclared_type` (survey).
    A type byte corrupted into one an FMT declares later is dropped once indexed (`_Index.early`), but
    the indexer keeps the 3 bytes as that type's length: its messages are found at their headers,
    each body then scanned byte by byte for the next one (about 4 us a byte; a payload's own 0xA3 0x95
    can then read as a header, as after any garbage). So is every message of a type whose FMT was
    refused."""

    refused = 0
    indexing = False

    def __setitem__(self, mtype, fmt) -> None:
        if fmt.len < 3:
            self.refused += 1
            return
        super().__setitem__(mtype, fmt)

    def __contains__(self, mtype) -> bool:
        return super().__contains__(mtype) or self._undeclared(mtype)

    def __missing__(self, mtype):
        if self._undeclared(mtype):
            return UNDECLARED
        raise KeyError(mtype)

    def _undeclared(self, mtype) -> bool:
        return self.indexing and isinstance(mtype, int) and 0 <= mtype < 256


class _Undeclared(DFReader.DFFormat):
    """The format of a header of a type no FMT declared: the header alone. DFReader also looks up the
    type an FMTU message names (in newer logs it reads the message's time stamp as that type): units
    given to this format are not kept."""

    def set_unit_ids(self, *args) -> None:
        pass

    def set_mult_ids(self, *args) -> None:
        pass


UNDECLARED = _Undeclared(0, "UNDECLARED", 3, "", "")


class _Index(DFReader.DFReader_binary):
    """DFReader's binary reader with its pure-Python indexer, checked formats and no GPS clock."""

    def __init__(self, *args, **kwargs):
        try:
            super().__init__(*args, **kwargs)
        except BaseException:       # a log too corrupt to index: the file DFReader opened is closed, not left
            for part in ("data_map", "filehandle"):
                if getattr(self, part, None) is not None:
                    getattr(self, part).close()
            raise

    early = 0                       # headers dropped for coming before their type's FMT (corrupt type bytes)

    def init_arrays(self, progress_callback=None):
        self.formats = _Formats(self.formats)
        self.formats.indexing = True
        try:
            super().init_arrays(progress_callback)
        finally:
            self.formats.indexing = False
        # what UNDECLARED left behind: its struct, cached under the type byte it was met with (DFReader
        # builds them again as it parses), and its message
        getattr(self, "unpackers", {}).clear()
        getattr(self, "messages", {}).pop("UNDECLARED", None)
        self._drop_before_fmt()

    def _drop_before_fmt(self) -> None:
        """A corrupt type byte can name a type whose FMT comes later in the log (ArduPilot writes some
        FMTs at their first use): that header, met before any FMT declared its type, is not one of its
        messages. Dropped, and counted (`early`)."""
        first: dict[int, int] = {}
        for o in self.offsets[FMT_TYPE]:
            if o + 3 < self.data_len:
                first.setdefault(self.data_map[o + 3], o)
        for t, offs in enumerate(self.offsets):
            if offs and t != FMT_TYPE and t in first and offs[0] < first[t]:
                kept = [o for o in offs if o > first[t]]
                self.early += len(offs) - len(kept)
                self.offsets[t] = kept

    def init_arrays_fast(self, progress_callback=None):
        self.init_arrays(progress_callback)

    def init_clock(self):
        self.clock = None


def open_index(path: str) -> _Index:
    """DFReader's index of the log at `path`; a SourceError naming the file if it cannot be made."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as e:
        raise SourceError(f"{path}: cannot open: {e.strerror}") from None
    if not looks_like_dataflash(head):
        raise SourceError(f"{path}: not a DataFlash log (no FMT message at its start)")
    try:
        with printed(stderr=True) as said:
            index = _Index(path)
    except Exception as e:      # noqa: BLE001 - DFReader raises anything on a corrupt FMT; one line for the user
        raise SourceError(f"{path}: DataFlash log not readable: {one_line(e)}") from None
    if said.lines:
        log.debug("%s: DFReader said %d lines, first: %s", path, said.lines,
                  "; ".join(line.strip() for line in said.first))
    return index


def one_line(e: Exception) -> str:
    """An exception as one printable line (a corrupt format character can be a newline)."""
    return f"{type(e).__name__}: " + repr(str(e))[1:-1]


def _time_column(fmt) -> tuple[str, int] | None:
    """The boot-time column of a format and its scale to microseconds."""
    if "TimeUS" in fmt.colhash:
        return "TimeUS", 1
    if fmt.name.startswith("GPS") and "T" in fmt.colhash:       # old GPS: TimeMS is the GPS time of week
        return "T", 1000
    if "TimeMS" in fmt.colhash:
        return "TimeMS", 1000
    return None


def _instance_number(name: str, base: str) -> int | None:
    """IMU -> 0, IMU2 -> 1, IMU3 -> 2 (older logs' instances); None: not an instance of base."""
    if name == base:
        return 0
    rest = name[len(base):]
    return int(rest) - 1 if name.startswith(base) and rest.isdigit() and int(rest) >= 2 else None


class Log:
    """Rows of chosen message types, decoded from DFReader's index with DFReader's formats."""

    def __init__(self, index: _Index):
        self.index = index
        self.data = index.data_map
        self.size = index.data_len

    def format(self, name: str):
        t = self.index.name_to_id.get(name)
        return None if t is None else self.index.formats.get(t)

    def offsets(self, name: str) -> list[int]:
        """Offsets of the complete messages of a type, in file order."""
        fmt = self.format(name)
        if fmt is None:
            return []
        offs = self.index.offsets[fmt.type]
        return offs[:-1] if offs and offs[-1] + fmt.len > self.size else offs

    def decoder(self, name: str, columns: list[str]) -> Callable[[int], tuple]:
        """A function: offset -> (boot time in us, then the values of `columns`, scaled by their
        format's multiplier; None for a column the format lacks)."""
        fmt = self.format(name)
        time_col, scale = _time_column(fmt) or (None, 0)
        unpack, data = struct.Struct(fmt.msg_struct).unpack_from, self.data
        n = len(fmt.msg_mults)      # a corrupt FMT can name more columns than it has format characters

        def index(column: str | None) -> int | None:
            i = fmt.colhash.get(column) if column else None
            return i if i is not None and i < n else None
        picks = [(i, None if i is None else fmt.msg_mults[i]) for i in map(index, columns)]
        it = index(time_col)

        def decode(ofs: int) -> tuple:
            e = unpack(data, ofs + 3)
            t = -1 if it is None else e[it] * scale
            return (t, *(None if i is None else e[i] * m if m else e[i] for i, m in picks))
        return decode

    def split(self, name: str, column: str) -> dict[int, list[int]]:
        """Offsets of a type's messages by the value of a one-byte column (an instance, an EKF core)."""
        fmt = self.format(name)
        i = fmt.colhash[column]
        k = 3 + struct.calcsize("<" + "".join(DFReader.FORMAT_TO_STRUCT[c][0] for c in fmt.format[:i]))
        data, out = self.data, {}
        for o in self.offsets(name):
            if o + k < self.size:
                out.setdefault(data[o + k], []).append(o)
        return out

    def instances(self, base: str) -> dict[int, tuple[str, list[int]]]:
        """(type name, offsets) of each instance of a sensor: IMU, IMU2, IMU3 or IMU rows by `I`."""
        out: dict[int, tuple[str, list[int]]] = {}
        for name in sorted(self.index.name_to_id):
            n = _instance_number(name, base)
            if n is None or not self.offsets(name):
                continue
            if "I" in self.format(name).colhash:
                out.update((i, (name, offs)) for i, offs in self.split(name, "I").items())
            else:
                out[n] = (name, self.offsets(name))
        return out

    def rows(self, name: str, columns: list[str], offsets: list[int] | None = None) -> Iterator[tuple]:
        """Decoded rows (time, *columns) of a type, all or at `offsets`; a row that cannot be
        unpacked (a format longer than its declared length, at the end of the file) is left out."""
        decode = self.decoder(name, columns)
        for o in self.offsets(name) if offsets is None else offsets:
            try:
                yield decode(o)
            except struct.error:
                continue

    def times(self, name: str, offsets: list[int]) -> list[int]:
        return [row[0] for row in self.rows(name, [], offsets)]

    def texts(self, name: str, column: str) -> Iterator[tuple[int, str]]:
        if self.format(name) is not None and column in self.format(name).colhash:
            for t, text in self.rows(name, [column]):
                yield t, DFReader.null_term(text)
