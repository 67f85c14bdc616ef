"""`UlogReader`: the samples of a PX4 ULog, its topics' streams merged by time stamp (microseconds
since the autopilot booted; `guard.sources.ulog.streams` gives each topic's units and frames)."""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np

from guard.errors import SourceError
from guard.model.samples import Sample, VehicleType
from guard.sources.base import LogSource
import guard.sources.ulog.survey as survey
from guard.sources.ulog.load import GPS_TOPICS, load
from guard.sources.ulog.streams import CHUNK, Stream, attitude_stream, gnss_stream, imu_stream, vehicle_stream
from guard.sources.ulog.verdicts import ekf_verdicts, message_verdicts


class UlogReader(LogSource):
    """Samples of a PX4 ULog in time order; `imu=N` reads vehicle_imu instance N instead of
    sensor_combined, `gnss=N` the GNSS receiver N (sensor_gps, or in older logs
    vehicle_gps_position, instance N); `system_id` is accepted for MAVLink's sake and ignored."""

    def __init__(self, path: str, system_id: int = 0, imu: int | None = None, gnss: int | None = None):
        super().__init__()
        self.path = path
        self.rates_hz: dict[str, float] = {}    # each stream read: its mean rate (what `notes` says)
        self.size = os.path.getsize(path) if os.path.isfile(path) else 0
        ulog, cut_at, walk = load(path)
        self.position = self.size           # pyulog has read the whole file
        survey.account(ulog, cut_at, walk, self.size, self.skipped, self.notes)
        sets = {(d.name, d.multi_id): d for d in ulog.data_list if "timestamp" in d.data}
        for (name, _), data in sets.items():
            self.messages[name] += len(data.data["timestamp"])
        self._streams = self._build(sets, imu, gnss)
        self.verdicts = sorted(ekf_verdicts(sets.get(("estimator_innovation_test_ratios", 0)),
                                            sets.get(("estimator_status", 0)), self.skipped)
                               + message_verdicts(ulog), key=lambda v: v["time_usec"])
        self._verdicts_on_clock()

    def _build(self, sets: dict, imu: int | None, gnss: int | None) -> list[Stream]:
        """The streams to merge, in the order samples of equal time go out: vehicle, attitude, IMU, GNSS."""
        gps_key = self._pick_gnss(sets, gnss)
        imu_key = ("sensor_combined", 0) if imu is None else ("vehicle_imu", imu)
        if imu is not None and imu_key not in sets:
            raise SourceError(f"{self.path}: no vehicle_imu instance {imu} "
                              f"(instances: {survey.instances(sets, 'vehicle_imu') or 'none'})")
        mag = sets.get(("vehicle_magnetometer", 0))
        streams = [self._stream(vehicle_stream, sets.get(("vehicle_status", 0))),
                   self._stream(attitude_stream, sets.get(("vehicle_attitude", 0))),
                   self._stream(imu_stream, sets.get(imu_key), mag),
                   self._stream(gnss_stream, sets.get(gps_key))]
        streams = [s for s in streams if s is not None]
        self.rates_hz = survey.note_streams(sets, streams, imu_key, gps_key, self.notes)
        if gps_key and gps_key[0] in GPS_TOPICS:
            self.date, self.utc_offset_us = survey.utc_date(sets[gps_key])
            # on the receiver's time, where the two part
            self.clock = clock = survey.gnss_clock(sets[gps_key], self.notes)
            if clock is not None:
                t0, rate = clock
                streams = [Stream(s.topic, (t0 + np.round((s.t_us - t0) * rate).astype(np.int64), *s.columns[1:]),
                                  s.make) for s in streams]
        return streams

    def _stream(self, build, data, *more) -> Stream | None:
        """`build(data, *more, skipped)` in time order; None when the topic is absent or lacks a field."""
        if data is None:
            return None
        try:
            stream = build(data, *more, self.skipped)
        except (KeyError, ValueError) as e:     # a field missing: an unknown version or a corrupt format
            self.notes.append(f"{data.name}: cannot be read ({type(e).__name__}: {e})")
            return None
        if stream is None:
            self.notes.append(f"{data.name}: none of the field layouts guard reads")
            return None
        if not bool(np.all(stream.t_us[1:] >= stream.t_us[:-1])):
            order = np.argsort(stream.t_us, kind="stable")
            stream = Stream(stream.topic, tuple(c[order] for c in stream.columns), stream.make)
        return stream

    def _pick_gnss(self, sets: dict, gnss: int | None) -> tuple[str, int] | None:
        """vehicle_gps_position (what the autopilot uses) by default; receiver N when asked."""
        if gnss is None:
            return next(((t, 0) for t in GPS_TOPICS if (t, 0) in sets), None)
        topic = "sensor_gps" if any(k[0] == "sensor_gps" for k in sets) else "vehicle_gps_position"
        if (topic, gnss) not in sets:
            raise SourceError(f"{self.path}: no GNSS receiver {gnss} "
                              f"({topic} instances: {survey.instances(sets, topic) or 'none'})")
        return topic, gnss

    def samples(self) -> Iterator[Sample]:
        """The streams merged by time stamp; at equal times in the order of `_build`."""
        streams = self._streams
        if not streams:
            return
        t = np.concatenate([s.t_us for s in streams])
        kind = np.concatenate([np.full(s.t_us.size, k, np.int8) for k, s in enumerate(streams)])
        order = np.lexsort((kind, t))
        t, kind = t[order], kind[order]
        rows = [s.rows() for s in streams]
        makes = [s.make for s in streams]
        for a in range(0, t.size, CHUNK):
            for k, t_us in zip(kind[a:a + CHUNK].tolist(), t[a:a + CHUNK].tolist()):
                sample = makes[k](next(rows[k]))
                if type(sample) is VehicleType:     # no time of its own
                    yield sample
                    continue
                if self.first_time_us is None:
                    self.first_time_us = t_us
                self.last_time_us = t_us
                yield sample
