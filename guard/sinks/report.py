"""The replay report (DESIGN.md's contract): a sink that keeps the alarms, clearances and notices,
and the JSON document built from them and from what the reader counted."""

from __future__ import annotations

import json
import math
import sys
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path

from guard.core.aiding.gnss import HELD_COURSE_MAX_MPS
from guard.model.events import Alarm, Cleared, Estimate, Notice
from guard.model.samples import Attitude, GnssFix, ImuSample
from guard.sinks.base import Sink

KINDS = {GnssFix: "gnss", ImuSample: "imu", Attitude: "attitude"}

# what each reason of the report's `skipped` means, in the words a replay prints it with
SKIPPED = {
    "gnss_no_fix": "GNSS messages without a 3D fix (monitoring waits for one, or coasts on the IMU)",
    "gnss_resent": "GNSS messages resent with a time already seen",
    "gnss_coarse_before_start": "GNSS fixes too coarse to start on (the receiver's accuracy over 5 m, or HDOP over 5)",
    "gnss_out_of_order": "GNSS messages stamped before the last one",
    "imu_resent": "IMU samples resent with a time already seen",
    "imu_out_of_order": "IMU samples stamped before the last one",
    "imu_before_first_fix": "IMU samples before the first GNSS fix (nothing to integrate them from)",
    "imu_too_slow": "IMU samples of a stream too slow to integrate (GNSS tested alone)",
    "imu_rate_unknown": "IMU samples of a stream first heard after guard went on GNSS alone without one, before its "
                        "rate was known (integrated from then on where it is fast enough)",
    "imu_no_compass": "IMU samples of an air vehicle without a compass, not integrated (GNSS tested alone)",
    "imu_impact": "IMU samples within 0.5 s of a blow over 3 g (a landing, a kerb): set aside, the GNSS holding",
    "imu_no_magnetometer": "IMU samples without any magnetometer reading (no heading reference)",
    "time_off_base": "samples stamped far off the stream's time base (a wild stamp, or a base never confirmed)",
    "new_base_at_end": "samples on a new time base the log ended before confirming (a run of one stream's, after "
                       "a reboot or a silence in its last seconds): not used",
    "new_base_held": "samples on a new time base (a reboot, or every stream back after a silence), held until the "
                     "base was confirmed (by the other stream, or by 3 s of their own): not used",
    "attitude_non_finite": "attitude messages with a non-finite or impossible roll or pitch",
    "gnss_bad_position": "GNSS fixes with an impossible position (or 0, 0)",
    "gnss_bad_velocity": "GNSS fixes with an impossible velocity",
    "imu_invalid": "IMU samples with a non-finite reading",
    "imu_not_new": "IMU messages marked as holding no new accelerometer or gyro reading (HIGHRES_IMU's fields_updated)",
    "imu_other_stream": "IMU messages of a second stream (RAW_IMU beside HIGHRES_IMU): the first one heard is read",
    "imu_out_of_range": "IMU samples beyond any sensor's range (corrupt data)",
    "time_implausible": "messages stamped past any boot or UNIX time (corrupt or forged)",
    "bad_message": "messages that could not be decoded",
    "bad_value": "messages with a value out of its type's range",
    "bad_transfer": "CAN transfers that could not be reassembled",
    "truncated": "messages cut short (the log's end, or a write the logger did not finish)",
    "garbage_bytes": "bytes between messages that were not a message",
    "unread_bytes": "bytes after the last readable message",
    "undeclared_type": "DataFlash messages of a type no FMT declared (a corrupt type byte, or a type whose FMT was "
                       "refused): stepped past to the next message",
    "bad_format": "messages of a format the log defines wrongly",
    "bad_crc": "MAVLink frames with a bad checksum",
    "other_system": "messages of another MAVLink system (--system-id 0 reads every system)",
    "ulog_bad_time": "ULog samples with an impossible time stamp",
    "ulog_corrupt": "ULog data the reader could not parse",
    "logger_dropouts": "gaps the ULog logger itself recorded (its dropouts)",
}

# what each reason of the report's `adjusted` means: samples used, not as they came
ADJUSTED = {
    "gnss_course_held": "GNSS fixes whose velocity direction the receiver held (a course repeated to the last "
                        f"digit under {HELD_COURSE_MAX_MPS:g} m/s): used with that direction taken as unknown",
    "gnss_manoeuvre_widened": "GNSS fixes on GNSS alone after a manoeuvre the IMU saw (its acceleration changed by "
                              "more than the model's random walk allows between fixes): tested against a model "
                              "widened by that change",
}


@dataclass
class Distances:
    """Distances from the estimate to the fixes: how many, their sum and largest, how many were far."""
    n: int = 0
    total: float = 0.0
    top: float = 0.0
    far: int = 0

    def add(self, d: float, far: bool) -> None:
        self.n += 1
        self.total += d
        self.top = max(self.top, d)
        self.far += far


class FixGap:
    """How far the estimate stood from each fix (after fusing it, or beside it when the GNSS is
    excluded): on a clean flight, within a few metres; coasting away from the fixes is what this
    shows. Kept apart too by whether the fix's position was fused: where an alarm excluded it, the
    estimate is held by the other sensors on purpose, and its distance from the fixes is the
    exclusion's."""

    FAR_M = 5.0

    def __init__(self):
        self.parts = {k: Distances() for k in ("all", "fused", "excluded")}

    def add(self, e: Estimate) -> None:
        if e.fix_en is None:
            return
        d = math.hypot(e.east_m - e.fix_en[0], e.north_m - e.fix_en[1])
        for key in ("all", "fused" if e.fix_fused else "excluded"):
            self.parts[key].add(d, d > self.FAR_M)

    def _of(self, key: str) -> dict:
        x = self.parts[key]
        n = max(x.n, 1)
        return {"max": round(x.top, 2), "mean": round(x.total / n, 2),
                f"share_over_{self.FAR_M:g}": round(x.far / n, 4), "fixes": x.n}

    def summary(self) -> dict:
        """max and mean (m), and the share of fixes more than FAR_M away, over all fixes; and the same of
        the fixes whose position was fused, and of those an alarm excluded."""
        return {**self._of("all"), "fused": self._of("fused"), "excluded": self._of("excluded")}


class ReportSink(Sink):
    def __init__(self):
        self.alarms: list[dict] = []
        self.cleared: list[dict] = []
        self.notices: list[dict] = []
        self.samples: Counter[str] = Counter()      # samples read, per kind
        self.gap = FixGap()

    def on_sample(self, sample) -> None:
        kind = KINDS.get(type(sample))
        if kind:
            self.samples[kind] += 1

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Alarm):
                self.alarms.append({"time_usec": e.t_us, "gnss_index": e.gnss_index, "sensor": e.sensor,
                                    "channel": e.channel, "statistic": e.statistic, "threshold": e.threshold,
                                    "offset": e.offset, "ambiguous_with": list(e.ambiguous_with),
                                    "standing": e.standing})
            elif isinstance(e, Cleared):
                self.cleared.append({"time_usec": e.t_us, "gnss_index": e.gnss_index, "sensor": e.sensor,
                                     "channel": e.channel})
            elif isinstance(e, Estimate):
                self.gap.add(e)
            elif isinstance(e, Notice):
                self.notices.append({"time_usec": e.t_us, "level": e.level, "text": e.text})

    def report(self, source, monitor, detector_cfg) -> dict:
        """The report of a replay of `source` (a LogSource) through `monitor`."""
        skipped = Counter(source.skipped) + monitor.skipped
        # what was still held for a new base when the log ended was no wild stamp, if a stream's run
        if at_end := min(monitor.timebase.unconfirmed(), skipped["time_off_base"]):
            skipped["time_off_base"] -= at_end
            skipped["new_base_at_end"] += at_end
            skipped = +skipped                      # no count of 0
        duration = 0.0 if source.first_time_us is None else (source.last_time_us - source.first_time_us) / 1e6
        return {
            "source": str(source.path),
            "format": type(source).__name__.removesuffix("Reader").lower(),
            "duration_s": round(duration, 3),
            "messages": dict(sorted(source.messages.items())),
            "skipped": dict(sorted(skipped.items())),
            "adjusted": dict(sorted(monitor.adjusted.items())),
            "detector": detector_cfg.name,
            "detector_config": json.loads(json.dumps(asdict(detector_cfg))),   # tuples as lists
            "gnss_samples": monitor.gnss_index + 1,
            "samples": dict(sorted(self.samples.items())),
            "rates_hz": {k: round(v, 2) for k, v in getattr(source, "rates_hz", {}).items()},
            "notes": list(source.notes),
            "autopilot": list(source.verdicts),     # the autopilot's own findings, where the log has them
            # where the log's clock was put on its receiver's (a note says so), every time in this report is
            # t0 + (logged - t0) rate, the log's own time stamps being `logged`; None: as logged
            "clock": None if source.clock is None else {"t0_usec": source.clock[0], "rate": source.clock[1]},
            "peak_ratio": {s: round(v, 3) for s, v in sorted(monitor.detector.peak.items())},
            "alarms": self.alarms,
            "cleared": self.cleared,
            "notices": self.notices,
            "estimate_to_fix_m": self.gap.summary(),
            # the compass's offset with the motors still (rad; guard.core.aiding.motors), what guard tune writes
            "compass_offset_still_rad": monitor.motors.still_offset(monitor.ekf),
            # the accelerometers' reading of gravity in the windows judged at rest (guard.core.aiding.rest)
            "accelerometers_at_rest": monitor.rest.summary(),
        }


def write_report(report: dict, out: str) -> None:
    text = json.dumps(report, indent=1) + "\n"
    if out == "-":
        sys.stdout.write(text)
    else:
        Path(out).write_text(text)
