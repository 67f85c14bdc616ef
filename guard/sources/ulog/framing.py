"""A ULog's message framing, walked before pyulog reads it, and mended where corrupt bytes broke it.

A ULog is a 16-byte header, then messages: a uint16 size, a type byte ('F', 'A', 'D', ...), then
`size` bytes. One corrupt size or type byte breaks the chain: pyulog then reads the next header from
the middle of a message and hops on by whatever sizes it finds there, until a sync message (which
older PX4 logs do not write) or chance puts it back on a boundary. One flipped byte in a public log
(Auterion's esc_status_log) cost it 31 of its 179 fixes.

`walk` follows the chain and checks each message against what the log itself has shown:
- its type is one ULog defines, its size is not 0 and it ends inside the file;
- a data message ('D') of a topic added before ('A') has its topic's size: the size of its format,
  as pyulog parses the log's definitions (pyulog requires it too), or where pyulog cannot, the size
  of the topic's first data message that CHAIN messages in a row follow (a topic's messages are one
  struct: every clean public ULog read here keeps one size per topic);
- any other message has its type's structure: a key's length inside the message, a sync message's
  8 bytes, a dropout's or a removal's 2, a format's ':', flag bits only first;
- the next message's header looks like one too (the check that catches a corrupt size).
Where a message fails, or the one after it, the chain broke. The walk looks on from the byte after
the message for the first place where CHAIN messages in a row pass, and skips to there: the corrupt
span is lost (the message that broke, if that place lies inside it, and what the walk could not
frame), and the rest is read. There, where nothing vouches for the place, each message must also
have its type's content: a key or a name in printable ASCII, a log level '0' to '7', a sync
message's magic bytes, a data message a topic added before (random bytes with a long size would
otherwise land the walk on a boundary far past the damage and lose what lies between). On the chain
the content is not asked: a byte flipped inside a format's or a key's text, or a data message of a
topic whose 'A' was lost, is left to pyulog to make what it can of (a format with one field's name
garbled still reads the other fields). A size that runs past the file's end, with no chain after
it, is the file's cut end: left for pyulog to stop at.

`mend` gives pyulog the file without the spans (None where nothing was skipped: the file as it is).
A file with data appended after the log (its flag bits give offsets into the file) is not mended:
removing bytes would move those offsets.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field

from pyulog import ULog

HEADER = 16                     # bytes of the file header before the first message
TYPES = frozenset(b"BFIMPQARDLCOS")     # the message types ULog defines
CHAIN = 4                       # messages in a row that must pass for the walk to take up again
_HEAD = struct.Struct("<HB")    # a message's size and type
_U16 = struct.Struct("<H")
_ANY_TYPE = re.compile(b"[" + bytes(sorted(TYPES)) + b"]")
_PRINTABLE = re.compile(rb"[\x20-\x7e]+")
_LEVELS = frozenset(b"01234567")
SYNC = bytes([0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12])
_A, _D, _B = ord("A"), ord("D"), ord("B")
_KEYED = {ord("I"): 0, ord("P"): 0, ord("M"): 1, ord("Q"): 1}     # where the key's length byte sits


def _shaped(buf, p: int, size: int, kind: int, strict: bool) -> bool:
    """Whether the `size` bytes after a header of type `kind` (not data) at p have that type's
    structure and, if `strict`, its content."""
    body = p + 3
    if kind in _KEYED:
        at = body + _KEYED[kind]
        if at >= body + size:
            return False
        n = buf[at]
        return 0 < n < body + size - at and (not strict or _PRINTABLE.fullmatch(buf[at + 1:at + 1 + n]) is not None)
    if kind == _A:
        return size > 3 and (not strict or _PRINTABLE.fullmatch(buf[body + 3:body + size]) is not None)
    if kind in (ord("L"), ord("C")):
        return size >= (9 if kind == ord("L") else 11) and (not strict or buf[body] in _LEVELS)
    if kind == ord("S"):
        return size == len(SYNC) and (not strict or buf[body:body + size] == SYNC)
    if kind in (ord("O"), ord("R")):
        return size == 2
    if kind == ord("F"):
        text = buf[body:body + size]
        return b":" in text and (not strict or _PRINTABLE.fullmatch(text) is not None)
    return p == HEADER      # flag bits: the first message only


@dataclass
class Walk:
    """What `walk` found: the spans (start, end) of the file's bytes that could not be framed."""
    spans: list[tuple[int, int]] = field(default_factory=list)
    messages: int = 0           # messages framed
    appended: bool = False      # the file has data appended (its flag bits say so): not walked

    @property
    def skipped_bytes(self) -> int:
        return sum(b - a for a, b in self.spans)

    def in_file(self, offset: int) -> int:
        """The file's offset of `offset` in the file without the spans (`mend`'s)."""
        for a, b in self.spans:
            if a <= offset:
                offset += b - a
        return offset


class _Chain:
    """The checks, with the topics ('A') and their data messages' sizes known as the walk goes: from the
    log's formats where pyulog can read them (`formats`: its message_formats), else learnt from a
    topic's first data message that CHAIN messages in a row follow."""

    def __init__(self, buf, formats: dict | None = None):
        self.buf, self.n, self.formats = buf, len(buf), formats
        self.topics: set[int] = set()
        self.sizes: dict[int, int] = {}                     # a topic's data messages' size
        self.ranges: dict[int, list[tuple[int, int]]] = {}  # ... where it may have several: the sizes its
        # format allows (padding), or those of each format an id was added with (a corrupt 'A' may take
        # another topic's id before that topic's own 'A'; pyulog then takes the later one)

    def head(self, p: int, strict: bool = True) -> tuple[int, int] | None:
        """(size, type) of a message that may start at p: None if it cannot (a type ULog does not
        define, size 0, a message past the file's end or not of its type's structure; if `strict`,
        not of its type's content or a data message of a topic not added)."""
        if p + 3 > self.n:
            return None
        size, kind = _HEAD.unpack_from(self.buf, p)
        if kind not in TYPES or size == 0:
            return None
        if kind == _D:
            if size < 2 or p + 5 > self.n:
                return None
            if strict and _U16.unpack_from(self.buf, p + 3)[0] not in self.topics:
                return None
        elif p + 3 + size > self.n or not _shaped(self.buf, p, size, kind, strict):
            return None
        return size, kind

    def whole(self, p: int, strict: bool = True) -> int | None:
        """Where the next message starts if one starts at p (`head`), ends inside the file and, being a
        data message, has its topic's size; else None."""
        h = self.head(p, strict)
        if h is None:
            return None
        size, kind = h
        end = p + 3 + size
        if end > self.n:
            return None
        if kind == _D:
            topic = _U16.unpack_from(self.buf, p + 3)[0]
            if self.sizes.get(topic, size) != size:
                return None
            if topic in self.ranges and not any(lo <= size <= hi for lo, hi in self.ranges[topic]):
                return None
        return end

    def holds(self, q: int) -> bool:
        """CHAIN whole messages in a row from q (or whole ones up to the file's end)."""
        for _ in range(CHAIN):
            if q == self.n:
                return True
            q = self.whole(q)
            if q is None:
                return False
        return True

    def take(self, p: int, end: int) -> None:
        """The message at p is whole: learn the topic it adds (and its size, from its format), or a
        topic's size from its first data message that CHAIN messages follow."""
        kind = self.buf[p + 2]
        if kind == _A and end - p >= 6:
            topic = _U16.unpack_from(self.buf, p + 4)[0]
            self.topics.add(topic)
            size = self._size(p, end)
            known = [(self.sizes[topic],) * 2] if topic in self.sizes else self.ranges.get(topic, [])
            if size is None or size in known:
                return
            if not known and size[0] == size[1]:
                self.sizes[topic] = size[0]
            else:           # a range, or an id added again with another format: any of them
                self.sizes.pop(topic, None)
                self.ranges[topic] = [*known, size]
        elif kind == _D:
            topic = _U16.unpack_from(self.buf, p + 3)[0]
            if topic in self.topics and topic not in self.sizes and topic not in self.ranges and self.holds(p):
                self.sizes[topic] = end - p - 3

    def _size(self, p: int, end: int) -> tuple[int, int] | None:
        """The least and most size of the data messages of the topic the 'A' at p adds, as pyulog
        parses its format (None where it cannot)."""
        if not self.formats:
            return None
        try:
            added = ULog._MessageAddLogged(bytes(self.buf[p + 3:end]), None, self.formats)
        except Exception:       # noqa: BLE001 - a format pyulog cannot parse: the size is learnt instead
            return None
        lo = added.dtype.itemsize
        return 2 + lo, 2 + max(added.max_data_size, lo)


def _appended(buf) -> bool:
    """Whether the file's first message is flag bits saying data is appended (incompat bit 0)."""
    if len(buf) < HEADER + 3 + 9:
        return False
    size, kind = _HEAD.unpack_from(buf, HEADER)
    return kind == _B and size >= 16 and bool(buf[HEADER + 3 + 8] & 1)


def walk(buf, formats: dict | None = None) -> Walk:
    """The framing of the ULog in `buf` (bytes), from its first message on; `formats`, pyulog's
    message_formats of its definitions, give each topic's size (else it is learnt)."""
    out = Walk(appended=_appended(buf))
    if out.appended:
        return out
    chain, n, p = _Chain(buf, formats), len(buf), HEADER
    head, u16, topics, sizes = _HEAD.unpack_from, _U16.unpack_from, chain.topics, chain.sizes
    while p + 3 <= n:
        # most messages: data of a topic whose size is known, before another topic's data (the checks
        # below for that case, unrolled)
        size, kind = head(buf, p)
        end = p + 3 + size
        if kind == _D and end + 5 <= n and sizes.get(u16(buf, p + 3)[0]) == size:
            next_size, next_kind = head(buf, end)
            if next_kind == _D and next_size >= 2 and u16(buf, end + 3)[0] in topics:
                out.messages += 1
                p = end
                continue
        end = chain.whole(p, strict=False)
        if end is not None:
            chain.take(p, end)      # a topic added here may be the next message's
            if end == n or chain.head(end, strict=False) is not None:
                out.messages += 1
                p = end
                continue
        q = _resume(chain, p + 1)
        if q is None:
            break           # nothing framed after p: the file's cut end (or all corrupt), pyulog's to stop at
        if end is not None and q >= end:
            out.messages += 1       # the message at p was whole: what broke came after it
            p = end
        out.spans.append((p, q))
        p = q
    return out


def _resume(chain: _Chain, p: int) -> int | None:
    """The first place from p where CHAIN messages in a row pass; None if none does."""
    buf, n = chain.buf, chain.n
    while True:
        m = _ANY_TYPE.search(buf, p + 2)
        if m is None:
            return None
        q = m.start() - 2
        if q + 3 > n:
            return None
        if chain.holds(q):
            return q
        p = q + 1


def mend(buf, formats: dict | None = None) -> tuple[bytes | None, Walk]:
    """The file without the spans `walk` could not frame (None: nothing to skip), and the walk."""
    w = walk(buf, formats)
    if not w.spans:
        return None, w
    parts, at = [], 0
    for a, b in w.spans:
        parts.append(buf[at:a])
        at = b
    parts.append(buf[at:])
    return b"".join(parts), w
