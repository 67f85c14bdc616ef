"""MCAP sink: a run's samples and events as a log that Foxglove opens without setup.

    /gnss/fix               foxglove.LocationFix (protobuf)  each GnssFix with a 3D fix
    /estimate/fix           foxglove.LocationFix (protobuf)  each Estimate, east/north variances as covariance
    /estimate/state         guard.EstimateState (JSON)       each Estimate: x and the diagonal of P
    /innovations/<sensor>   guard.Innovation (JSON)          each Tested: r, diag(S), statistic, threshold
                                                             (modelled: false where S was widened past the
                                                             sensor's model, a held course)
    /alarms                 guard.Alarm (JSON)               each Alarm (kind "alarm") and Cleared ("cleared")
    /log                    foxglove.Log (protobuf)          alarms (ERROR), cleared (INFO), notices

Times are UTC where the source knows it, so that Foxglove's timeline shows the flight's own date and
time: log_time = publish_time = (t_us + the source's utc_offset_us) * 1000, integer nanoseconds, and the
same in the messages' timestamps; the vehicle's own time (since boot) stays in every JSON record's
`t_us`. A time stamp that is already UTC (past 2001 in unix microseconds) is taken as it is; with no
offset known (a log that does not say), the vehicle's time. `clock` is anything with a `utc_offset_us`
attribute (a log source, the daemon's wall clock), read at every message: an offset learnt late or
changed by an autopilot reboot applies from then on.

Every file holds a Metadata record named "guard" (the config in effect, defaults included, and where
the data came from). Chunks are zstd-compressed; a finished chunk is handed to the OS at once, and an
alarm finishes its chunk and syncs it to the disk, so a crash loses at most the chunk being filled and
never an alarm; `recover` rebuilds a finished file from what is left.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import struct
import time

import numpy as np
import zstandard
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from guard import __version__
from guard.errors import SourceError
from guard.model.events import UNITS, Alarm, Cleared, Estimate, Notice, Tested
from guard.model.samples import GnssFix
from guard.sinks.base import Sink

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
UNIX_2001_US = 978_307_200_000_000      # a time stamp past this is UTC already, not time since boot
RETRY_S = 30.0   # vehicle time between attempts to open a new file after an I/O error

_NUM = {"type": ["number", "null"]}          # null stands for NaN and inf, which JSON cannot carry
_NUMS = {"type": "array", "items": _NUM}
_INT, _STR, _BOOL = {"type": "integer"}, {"type": "string"}, {"type": "boolean"}
JSON_SCHEMAS = {
    "guard.EstimateState": dict(
        t_us=_INT, gnss_index=_INT, east_m=_NUM, north_m=_NUM, yaw_rad=_NUM, x=_NUMS, P_diag=_NUMS),
    "guard.Innovation": dict(
        t_us=_INT, gnss_index=_INT, sensor=_STR, channels={"type": "array", "items": _STR}, r=_NUMS,
        S_diag=_NUMS, statistic=_NUMS, threshold=_NUMS, fused=_BOOL, modelled=_BOOL),
    "guard.Alarm": dict(
        kind={"enum": ["alarm", "cleared"]}, t_us=_INT, gnss_index=_INT, sensor=_STR, channel=_STR,
        statistic=_NUM, threshold=_NUM, offset=_NUM, detector=_STR, standing=_BOOL),
}
PROTO_CLASSES = {cls.DESCRIPTOR.full_name: cls for cls in (LocationFix, Log)}


def _num(v) -> float | None:
    return float(v) if math.isfinite(v) else None


def _nums(a) -> list[float | None]:
    return [_num(v) for v in np.ravel(a)]


def _stamp(t_us: int) -> Timestamp:
    """t_us: UTC (or vehicle) microseconds, as _utc gives them."""
    return Timestamp(seconds=t_us // 1_000_000, nanos=(t_us % 1_000_000) * 1000)


def _schema(name: str) -> tuple[str, bytes]:
    """(encoding, data) of a schema: a JSON Schema, or a FileDescriptorSet of the message's file and imports."""
    if name in JSON_SCHEMAS:
        schema = {"title": name, "type": "object", "properties": JSON_SCHEMAS[name]}
        return "jsonschema", json.dumps(schema).encode()
    fds, seen = FileDescriptorSet(), set()

    def add(file):   # dependencies first, each once
        for dep in file.dependencies:
            if dep.name not in seen:
                seen.add(dep.name)
                add(dep)
        file.CopyToProto(fds.file.add())

    add(PROTO_CLASSES[name].DESCRIPTOR.file)
    return "protobuf", fds.SerializeToString()


class McapLog(Sink):
    """Writes samples and events to MCAP files, rotated by size (`rotate_mb`) or vehicle time (`rotate_s`).

    `path_or_dir` is a file (`run.mcap`, then `run-1.mcap`, ... on rotation; overwritten) or a directory
    (`guard-YYYYmmdd-HHMMSS[-N].mcap`, UTC wall clock, never overwritten; created when missing). In a
    directory, `keep_mb` bounds guard's own files: each time one opens, the oldest go until the rest fit.
    I/O errors never reach the caller: they are logged once per outage, counted in `errors`, and messages
    are dropped (`lost_messages`) until a new file opens at the next rotation or after RETRY_S of vehicle time.
    """

    def __init__(self, path_or_dir: str, *, rotate_mb: float | None = None, rotate_s: float | None = None,
                 chunk_size: int = 256 * 1024, metadata: dict[str, str] | None = None, keep_mb: float | None = None,
                 clock=None):
        self.clock = clock                # its utc_offset_us: vehicle time + it = UTC (module docstring)
        self._target = os.fspath(path_or_dir)
        self._keep_bytes = None if not keep_mb else int(keep_mb * 1e6)
        self._is_dir = os.path.isdir(self._target) or not self._target.endswith(".mcap")
        self._rotate_bytes = None if rotate_mb is None else int(rotate_mb * 1e6)
        self._rotate_us = None if rotate_s is None else int(rotate_s * 1e6)
        self._chunk_size = chunk_size
        self._metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
        self.path: str | None = None      # the file being written
        self.files: list[str] = []        # every file opened, in order
        self.errors = 0
        self.lost_messages = 0
        self._stream = self._writer = None
        self._ids: dict[str, int] = {}    # topic or schema name -> id, in the current file
        self._parts = 0                   # attempts to open a file
        self._pos = 0                     # bytes handed to the stream, at the last finished chunk
        self._unflushed = 0               # messages in the chunk being filled
        self._t0_us: int | None = None    # first message in the current file
        self._quiet_from_us = 0           # while quiet: vehicle time of the last failure ...
        self._retry_at_us: int | None = None   # ... and of the next attempt to open a file
        self._failed = False              # an outage is logged; quiet until a file opens again
        self._closed = False
        self._open(None)

    # -- listener interface ------------------------------------------------------------------------------
    def on_sample(self, sample) -> None:
        """Logs a GnssFix with a 3D fix; other samples are not logged."""
        if isinstance(sample, GnssFix) and sample.fix_ok:
            fix = LocationFix(timestamp=_stamp(self._utc(sample.t_us)), frame_id="gnss", latitude=sample.lat_deg,
                              longitude=sample.lon_deg, altitude=sample.alt_m,
                              velocity=Vector3(x=sample.vel_e_mps, y=sample.vel_n_mps))
            if sample.h_acc_m is not None:   # ENU, row-major; the receiver gives no vertical accuracy here
                var = sample.h_acc_m ** 2
                fix.position_covariance.extend([var, 0, 0, 0, var, 0, 0, 0, 0])
                fix.position_covariance_type = LocationFix.APPROXIMATED
            self._proto("/gnss/fix", sample.t_us, fix)

    def on_events(self, events: list) -> None:
        """Logs Estimate, Tested, Alarm, Cleared and Notice; a bare Innovation (no statistic) is skipped."""
        for ev in events:
            if isinstance(ev, Estimate):
                self._estimate(ev)
            elif isinstance(ev, Tested):
                self._tested(ev)
            elif isinstance(ev, Alarm):
                self._alarm(ev)
            elif isinstance(ev, Cleared):
                self._json("/alarms", "guard.Alarm", ev.t_us, dict(
                    kind="cleared", t_us=ev.t_us, gnss_index=int(ev.gnss_index), sensor=ev.sensor,
                    channel=ev.channel))
                self._log(ev.t_us, Log.INFO, f"cleared {ev.sensor}/{ev.channel} (GNSS sample {ev.gnss_index})")
            elif isinstance(ev, Notice):
                self._log(ev.t_us, Log.WARNING if ev.level == "warning" else Log.INFO, ev.text)

    def close(self) -> None:
        """Finishes the current file (summary, footer). Later calls and messages do nothing."""
        if not self._closed:
            self._finish(None)
            self._closed = True

    # -- messages ----------------------------------------------------------------------------------------
    def _estimate(self, ev: Estimate) -> None:
        P = np.ravel(ev.P_diag)
        lat, lon = ev.lat_lon()
        self._proto("/estimate/fix", ev.t_us, LocationFix(
            timestamp=_stamp(self._utc(ev.t_us)), frame_id="estimate", latitude=lat, longitude=lon,
            # ENU, row-major: var(east), var(north); the state has no altitude
            position_covariance=[float(P[0]), 0, 0, 0, float(P[1]), 0, 0, 0, 0],
            position_covariance_type=LocationFix.DIAGONAL_KNOWN,
            heading=(math.pi / 2 - ev.yaw_rad) % (2 * math.pi)))    # ENU yaw -> clockwise from north
        self._json("/estimate/state", "guard.EstimateState", ev.t_us, dict(
            t_us=ev.t_us, gnss_index=int(ev.gnss_index), east_m=_num(ev.east_m), north_m=_num(ev.north_m),
            yaw_rad=_num(ev.yaw_rad), x=_nums(ev.x), P_diag=_nums(P)))

    def _tested(self, ev: Tested) -> None:
        inn = ev.innovation
        self._json(f"/innovations/{inn.sensor}", "guard.Innovation", inn.t_us, dict(
            t_us=inn.t_us, gnss_index=int(ev.gnss_index), sensor=inn.sensor, channels=list(inn.channels),
            r=_nums(inn.r), S_diag=_nums(np.diag(np.atleast_2d(inn.S))), statistic=_nums(ev.statistic),
            threshold=_nums(ev.threshold), fused=bool(inn.fused),
            modelled=bool(inn.modelled)))

    def _alarm(self, ev: Alarm) -> None:
        self._json("/alarms", "guard.Alarm", ev.t_us, dict(
            kind="alarm", t_us=ev.t_us, gnss_index=int(ev.gnss_index), sensor=ev.sensor, channel=ev.channel,
            statistic=_num(ev.statistic), threshold=_num(ev.threshold), offset=_num(ev.offset),
            detector=ev.detector, standing=bool(ev.standing)))
        self._log(ev.t_us, Log.ERROR,
                  f"ALARM{' (standing, again)' if ev.standing else ''} "
                  f"{ev.sensor}/{ev.channel}: {ev.detector} statistic {ev.statistic:.3g} > threshold "
                  f"{ev.threshold:.3g}, offset {ev.offset:+.3g} {UNITS.get(ev.sensor, '')} "
                  f"(GNSS sample {ev.gnss_index})")
        self.sync()

    def sync(self) -> None:
        """Finish the chunk being filled and put it on the disk (an alarm must survive a crash right
        after it). Costs a chunk's compression ratio, so only at an alarm."""
        if self._writer is None:
            return
        try:
            self._writer.flush()
            os.fsync(self._stream.fileno())
            self._pos, self._unflushed = self._stream.tell(), 0
        except OSError as exc:
            self.lost_messages += self._unflushed
            self._fail(exc, None)

    def _log(self, t_us: int, level: int, text: str) -> None:
        self._proto("/log", t_us, Log(timestamp=_stamp(self._utc(t_us)), level=level, message=text, name="guard"))

    def note(self, t_us: int, level: str, text: str) -> None:
        """An operator line that is not the core's (a silent link, a lost stream) into /log too."""
        self._log(t_us, Log.WARNING if level == "warning" else Log.INFO, text)

    def _utc(self, t_us: int) -> int:
        """The time a message is logged at: UTC where known (module docstring)."""
        if t_us >= UNIX_2001_US:
            return t_us
        offset = getattr(self.clock, "utc_offset_us", None)
        return t_us + offset if offset and t_us + offset > 0 else t_us

    def _json(self, topic: str, schema: str, t_us: int, record: dict) -> None:
        self._write(topic, schema, "json", t_us, json.dumps(record, allow_nan=False).encode())

    def _proto(self, topic: str, t_us: int, msg) -> None:
        self._write(topic, msg.DESCRIPTOR.full_name, "protobuf", t_us, msg.SerializeToString())

    def _write(self, topic: str, schema: str, encoding: str, t_us: int, data: bytes) -> None:
        if self._closed:
            return
        if self._writer is None:
            if self._retry_at_us is None:
                self._quiet_from_us, self._retry_at_us = t_us, t_us + int(RETRY_S * 1e6)
            # wait for the retry time, unless the vehicle's clock went back (autopilot reboot)
            if self._quiet_from_us <= t_us < self._retry_at_us or not self._open(t_us):
                self.lost_messages += 1
                return
        elif self._t0_us is not None and (
                (self._rotate_bytes is not None and self._pos >= self._rotate_bytes)
                or (self._rotate_us is not None and t_us - self._t0_us >= self._rotate_us)):
            self._finish(t_us)
            if not self._open(t_us):
                self.lost_messages += 1
                return
        try:
            if self._t0_us is None:
                self._t0_us = t_us
            if topic not in self._ids:
                if schema not in self._ids:
                    self._ids[schema] = self._writer.register_schema(schema, *_schema(schema))
                self._ids[topic] = self._writer.register_channel(topic, encoding, self._ids[schema])
            self._unflushed += 1
            t_ns = self._utc(t_us) * 1000
            self._writer.add_message(self._ids[topic], t_ns, data, t_ns)
            if self._stream.tell() != self._pos:   # a chunk was finished: hand it to the OS now
                self._stream.flush()
                self._pos, self._unflushed = self._stream.tell(), 0
        except OSError as exc:
            self.lost_messages += self._unflushed
            self._fail(exc, t_us)

    # -- files -------------------------------------------------------------------------------------------
    def _next_path(self) -> str:
        self._parts += 1
        if not self._is_dir:
            return self._target if self._parts == 1 else f"{self._target[:-5]}-{self._parts - 1}.mcap"
        stem = os.path.join(self._target, time.strftime("guard-%Y%m%d-%H%M%S", time.gmtime()))
        path, n = stem + ".mcap", 0
        while os.path.exists(path):
            n += 1
            path = f"{stem}-{n}.mcap"
        return path

    def _open(self, t_us: int | None) -> bool:
        path = self._next_path()
        try:
            if self._is_dir:
                os.makedirs(self._target, exist_ok=True)
            self._stream = open(path, "xb" if self._is_dir else "wb")
            self._writer = Writer(self._stream, chunk_size=self._chunk_size, compression=CompressionType.ZSTD)
            self._writer.start(library=f"guard {__version__}; {LIBRARY_IDENTIFIER}")
            self._writer.add_metadata("guard", self._metadata)
            self._stream.flush()
        except OSError as exc:
            self._fail(exc, t_us)
            return False
        if self._failed:
            log.warning("MCAP log resumed in %s (%d messages lost)", path, self.lost_messages)
        self.path, self._failed, self._retry_at_us = path, False, None
        self.files.append(path)
        self._ids, self._pos, self._unflushed, self._t0_us = {}, self._stream.tell(), 0, None
        if self._is_dir and self._keep_bytes is not None:
            self._prune()
        return True

    def _prune(self) -> None:
        """Delete guard's oldest files in the directory until the others fit in keep_mb (the one being
        written stays). Their names are UTC times: sorted, the oldest come first."""
        names = sorted(n for n in os.listdir(self._target) if n.startswith("guard-") and n.endswith(".mcap"))
        old = [os.path.join(self._target, n) for n in names if os.path.join(self._target, n) != self.path]
        sizes = {p: os.path.getsize(p) for p in old}
        total = sum(sizes.values())
        for p in old:
            if total <= self._keep_bytes:
                break
            try:
                os.remove(p)
                log.info("MCAP log %s deleted: the directory holds at most its keep_mb", p)
            except OSError as exc:
                log.warning("MCAP log %s could not be deleted: %s", p, exc.strerror)
            total -= sizes[p]

    def _finish(self, t_us: int | None) -> None:
        if self._writer is None:
            return
        try:
            self._writer.finish()
            self._stream.close()
        except OSError as exc:
            self.lost_messages += self._unflushed
            self._fail(exc, t_us)
        self._stream = self._writer = self.path = None

    def _fail(self, exc: OSError, t_us: int | None) -> None:
        """Counts an I/O error, logs it once per outage, drops the file and plans the next attempt."""
        self.errors += 1
        if not self._failed:
            log.error("MCAP log lost: %s", exc)
        self._failed = True
        if self._stream is not None:
            with contextlib.suppress(OSError):   # already reported; the file is given up
                self._stream.close()
        self._stream = self._writer = self.path = None
        retry = None if t_us is None else t_us + int(RETRY_S * 1e6)
        if retry is not None and self._rotate_us is not None and self._t0_us is not None:
            retry = min(retry, self._t0_us + self._rotate_us)
        self._quiet_from_us, self._retry_at_us, self._t0_us = t_us or 0, retry, None


def recover(src: str, dst: str) -> tuple[int, int]:
    """Copies every complete record of a cut MCAP (crash before `finish`) into a finished MCAP at dst.

    Schemas, channels, metadata, attachments and messages are read in a stream up to the first record that
    cannot be read (the cut). Returns (messages recovered, channels recovered). Raises SourceError when
    src cannot be opened or is not an MCAP file.
    """
    try:
        fin = open(src, "rb")
    except OSError as exc:
        raise SourceError(f"cannot read {src}: {exc}") from exc
    with fin:
        if fin.read(len(MAGIC)) != MAGIC:
            raise SourceError(f"{src} is not an MCAP file")
        fin.seek(0)
        with open(dst, "wb") as fout:
            writer = Writer(fout, compression=CompressionType.ZSTD)
            messages, channels, cut = _copy(StreamReader(fin, validate_crcs=True).records, writer)
            if cut is not None:
                log.warning("%s: unreadable from byte %d on (%s); kept what came before", src, fin.tell(),
                            type(cut).__name__)
            writer.finish()
    return messages, channels


def _copy(records, writer: Writer) -> tuple[int, int, Exception | None]:
    """Starts the writer and copies records up to the first unreadable one: (messages, channels, its error)."""
    schemas: dict[int, int] = {0: 0}   # id in src -> id in dst
    channels: dict[int, int] = {}
    messages, started, cut = 0, False, None
    try:
        for rec in records:
            if not started:
                hdr = rec if isinstance(rec, Header) else Header("", LIBRARY_IDENTIFIER)
                writer.start(hdr.profile, hdr.library)
                started = True
            if isinstance(rec, Schema) and rec.id not in schemas:
                schemas[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel) and rec.id not in channels:
                channels[rec.id] = writer.register_channel(
                    rec.topic, rec.message_encoding, schemas.get(rec.schema_id, 0), rec.metadata)
            elif isinstance(rec, Message) and rec.channel_id in channels:
                writer.add_message(channels[rec.channel_id], rec.log_time, rec.data, rec.publish_time,
                                   rec.sequence)
                messages += 1
            elif isinstance(rec, Metadata):
                writer.add_metadata(rec.name, rec.metadata)
            elif isinstance(rec, Attachment):
                writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
    except (McapError, struct.error, ValueError, zstandard.ZstdError) as exc:
        cut = exc
    if not started:
        writer.start()
    return messages, len(channels), cut
