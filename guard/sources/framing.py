"""MAVLink framing for the live link (`guard.sources.link`): bytes to CRC-checked frames, and the
MAVLink 2 signature check, both before pymavlink decodes or records anything.

`split(data, final)` finds the frames in `data`. Every start byte (0xFD for MAVLink 2, 0xFE for
MAVLink 1) is a candidate; a candidate whose header is impossible (unknown incompatibility flags,
a message id the dialect lacks) or whose CRC fails is not a frame, and the scan goes on from the
*next byte*, not past the length the candidate claimed: a stray start byte costs no frame after it.
A frame of a message the dialect lacks cannot be CRC-checked, so it is skipped as bad bytes.

- `final=True` (a UDP datagram): the data is all there is. Bytes left at the end from a plausible
  start that runs past the end are a partial frame, dropped: never joined with the next datagram.
- `final=False` (a TCP or serial stream): parsing stops at a candidate that may still complete, and
  `rest` says where; the caller keeps data[rest:] (under MAX_FRAME bytes) for the next read.

`verify(frame, signing, require_signed)` checks a frame against pymavlink's signing state without
changing it: the HMAC first (sha256(key + header + payload + crc + link_id + timestamp)[:6]), then
the time stamp against the stream's last one, so that only a frame that pymavlink will accept
reaches it. pymavlink records a stream's time stamp before it checks the signature: a forged frame
stamped 2^48 - 2 would otherwise lock out the genuine stream.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import re
from typing import NamedTuple

os.environ.setdefault("MAVLINK20", "1")     # before pymavlink is imported, or frames are MAVLink 1

from pymavlink.dialects.v20 import ardupilotmega as mavlink     # noqa: E402

V1, V2 = mavlink.PROTOCOL_MARKER_V1, mavlink.PROTOCOL_MARKER_V2     # 0xFE, 0xFD
SIGNED = mavlink.MAVLINK_IFLAG_SIGNED
SIGNATURE_LEN = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN                 # link id 1, time stamp 6, signature 6
MAX_FRAME = mavlink.HEADER_LEN_V2 + 255 + 2 + SIGNATURE_LEN         # 280 bytes
NEW_STREAM_SLACK = 6_000_000        # 10 us units: a new stream may start up to 60 s behind our clock (pymavlink)
_START = re.compile(rb"[\xfd\xfe]")


class Frame(NamedTuple):
    buf: bytes
    system: int
    component: int
    msg_id: int
    signed: bool


class Split(NamedTuple):
    frames: list[Frame]
    bad: int            # runs of bytes that are no frame
    partial: int        # 1 when a datagram ends inside a frame
    rest: int           # data[rest:] is still unparsed (a stream's incomplete frame)


def _header(data: bytes, j: int) -> tuple[int | None, bool]:
    """(frame length or None while too few bytes are there to tell, plausible so far) of the candidate at j."""
    n = len(data) - j
    if data[j] == V2:
        if n >= 3 and data[j + 2] & ~SIGNED:
            return None, False                          # an incompatibility flag we do not know
        if n >= 10 and (data[j + 7] | data[j + 8] << 8 | data[j + 9] << 16) not in mavlink.mavlink_map:
            return None, False
        if n < 3:
            return None, True
        return mavlink.HEADER_LEN_V2 + data[j + 1] + 2 + (SIGNATURE_LEN if data[j + 2] & SIGNED else 0), True
    if n >= 6 and data[j + 5] not in mavlink.mavlink_map:
        return None, False
    if n < 2:
        return None, True
    return mavlink.HEADER_LEN_V1 + data[j + 1] + 2, True


def _frame(data: bytes, j: int, length: int) -> Frame | None:
    """The frame at data[j:j+length], or None when its CRC fails."""
    buf = bytes(data[j:j + length])
    v2 = buf[0] == V2
    hlen = mavlink.HEADER_LEN_V2 if v2 else mavlink.HEADER_LEN_V1
    signed = v2 and bool(buf[2] & SIGNED)
    msg_id = buf[7] | buf[8] << 8 | buf[9] << 16 if v2 else buf[5]
    end = hlen + buf[1]
    # CRC-16/MCRF4XX over the header (without the start byte) and payload, then the message's crc_extra
    crc = mavlink.x25crc(buf[1:end])
    crc.accumulate(bytes((mavlink.mavlink_map[msg_id].crc_extra,)))
    if crc.crc != buf[end] | buf[end + 1] << 8:
        return None
    system, component = (buf[5], buf[6]) if v2 else (buf[3], buf[4])
    return Frame(buf, system, component, msg_id, signed)


def split(data: bytes, final: bool = True) -> Split:
    """The frames in `data`, with counts of what was not one (see the module docstring)."""
    frames: list[Frame] = []
    bad = partial = 0
    i = 0                   # data[:i] is done with: frames, and bad runs already counted
    j = 0                   # the next candidate is searched from here
    n = len(data)
    incomplete = None       # the first plausible candidate in data[i:] that runs past the end
    while (m := _START.search(data, j)) is not None:
        j = m.start()
        length, plausible = _header(data, j)
        if plausible and (length is None or j + length > n):
            if not final:
                break
            if incomplete is None:
                incomplete = j
            j += 1
            continue
        frame = _frame(data, j, length) if plausible else None
        if frame is None:
            j += 1
            continue
        if j > i:
            bad += 1
        frames.append(frame)
        i = j = j + length
        incomplete = None
    else:
        j = n
    if not final:                        # a stream: keep what may still become a frame
        if j > i:
            bad += 1
        return Split(frames, bad, 0, j)
    if incomplete is not None:          # bad bytes, if any, then the frame the datagram cut off
        bad += 1 if incomplete > i else 0
        partial = 1
    elif i < n:
        bad += 1
    return Split(frames, bad, partial, n)


def verify(frame: Frame, signing, require_signed: bool) -> str | None:
    """Why `frame` must be dropped under pymavlink's MAVLinkSigning state `signing` (None: accept).

    Reads `signing` (secret_key, timestamp, stream_timestamps) and changes nothing: pymavlink's own
    check, when it decodes the frame, records the time stamp of a frame that passed this one.
    """
    if signing.secret_key is None:
        return None
    if not frame.signed:
        return "unsigned" if require_signed else None
    buf = frame.buf
    # signature = sha256(secret_key + header + payload + crc + link_id + timestamp)[:6]
    expected = hashlib.sha256(signing.secret_key + buf[:-6]).digest()[:6]
    if not hmac.compare_digest(expected, buf[-6:]):
        return "wrong signature"
    link_id = buf[-13]
    timestamp = int.from_bytes(buf[-12:-6], "little")      # 10 us units since 2015-01-01
    last = signing.stream_timestamps.get((link_id, frame.system, frame.component))
    if last is not None and timestamp <= last:
        return "replayed time stamp"
    if last is None and timestamp + NEW_STREAM_SLACK < signing.timestamp:
        return "new stream's time stamp too old"
    return None
