"""Whose clock a sample is on: the stream's own time base, a reboot's new one, or a lone wild stamp.

The core's time is the samples' own (`t_us`, the autopilot's boot time). A sample off the current
base (behind it by more than BACKWARD_US, a fix by more than LATE_FIX_US, as a receiver stamps a fix
at its time of validity and sends it a latency later; or ahead by more than `max_gap_s`) is held, not
taken:
- an autopilot reboot, or a link back after a long outage, moves every stream: the new base is
  confirmed when a GNSS fix and an IMU sample (each kind that has been heard) agree on it, within
  `max_gap_s` of each other; the filter then starts again on it;
- a stream whose partner has fallen silent (an IMU stream that stopped, then a GNSS silence over
  `max_gap_s`) confirms a new base alone: its held samples spanning SOLE_SPAN_US by their own stamps,
  each within SOLE_STEP_US of the latest (one out of order breaks no run), no sample of another kind
  heard in between (before, it waited for the silent kind for good, and nothing was monitored
  again). Stray frames do not: forged ones must come as a run of a stream, which does no more than
  a forged fix and IMU sample already can (below);
  What was held until a base was confirmed is not used (the filter starts again on the sample that
  confirmed it) and is counted as `new_base_held`, apart from the wild stamps;
- a lone frame with a wild time stamp (a glitch, or a forged frame) is dropped and counted
  (`time_off_base`). One
  stamped ahead within `max_gap_s` is on the base and is taken: it moves the filter's time on, the
  genuine streams held behind it then agree on theirs, and guard starts again there (a forged frame
  can do that much, and no more: a GNSS alarm stands through it).
A sample on the base but older than the last of its own stream (out of order, or the same again) is
dropped and counted too: the filter never runs backwards.

The base is the filter's time, or, while there is no filter (before the first fix, and after a
restart until the next one), the latest sample taken of the same kind (a fix may be stamped at its
time of validity, some hundreds of milliseconds behind the IMU's latest): a lone wild stamp before
the first fix is dropped as one after it is (it had become every later sample's "last", and all of
them were dropped as out of order).

On GNSS alone (an IMU too slow to integrate, or no compass) the filter's time moves with the fixes
only; the IMU, not integrated, keeps the clock through a GNSS silence by its own continuity (each
sample within OWN_STEP_US of its last), and a fix that comes more than `max_gap_s` after the last one,
where the IMU's latest sample is (within CONFIRM_US), ends a silence: the monitor starts a new filter
on it and says so. A lone fix stamped far ahead of both is still a wild stamp, dropped. Forged IMU
frames each within OWN_STEP_US of the last can walk that clock (one frame cannot), as a forged fix
and IMU sample agreeing on a new base can re-initialise guard at any time (a reboot's rule).
"""

from __future__ import annotations

from collections import Counter

BACKWARD_US = 200_000       # a stream this far behind the filter is off its base (a reboot, a wild stamp)
LATE_FIX_US = 1_000_000     # ... but a fix, stamped at its time of validity, may come this late (its latency)
OWN_STEP_US = 3_000_000     # an IMU the filter does not follow keeps its own clock: its next sample this soon
CONFIRM_US = 1_000_000      # a fix this close to the IMU's latest sample is on the clock the IMU kept
SOLE_SPAN_US = 3_000_000    # one kind's held samples this long, no other kind heard, confirm a base alone,
SOLE_STEP_US = 2_500_000    # ... each within this of the last (a stream's run, a 1 Hz one with samples lost
                            # or its clock off, not stray frames)


class Timebase:
    def __init__(self, max_gap_s: float, skipped: Counter):
        self.max_gap_us = max_gap_s * 1e6
        self.skipped = skipped
        self.heard: set[str] = set()                # the kinds of sample heard so far ("gnss", "imu")
        self.last: dict[str, int] = {}              # the last time stamp taken, per kind
        # kind -> (its first held sample's time, the first of its latest run, the latest, count) off the base
        self.candidate: dict[str, tuple[int, int, int, int]] = {}
        self.sole: tuple[str, int] | None = None    # (kind, its first held sample's time) of a base it confirmed alone

    def reset(self) -> None:
        self.last.clear()
        self.candidate.clear()

    def check(self, kind: str, t_us: int, now_us: int | None, own_clock: bool = False) -> str:
        """"take", "drop", or "rebase" (a new time base confirmed: start again on it). `now_us`: the
        filter's time (None without a filter: the latest sample of this kind taken is the base).
        `own_clock`: on GNSS alone, where the filter does not follow the IMU, an IMU sample within
        OWN_STEP_US after its last is on the base however far ahead of the filter's time (never one
        behind it: a fix forged ahead, within max_gap_s, moves the filter's time on, and the genuine
        streams held behind it confirm the base they are on, as before)."""
        self.heard.add(kind)
        if now_us is None:
            now_us = self.last.get(kind)
        last = self.last.get(kind)
        goes_on = own_clock and kind == "imu" and last is not None and 0 < t_us - last <= OWN_STEP_US
        back_us = LATE_FIX_US if kind == "gnss" else BACKWARD_US
        if now_us is not None and (t_us < now_us - back_us or (t_us > now_us + self.max_gap_us and not goes_on)):
            c = self.candidate
            if any(abs(t_us - t) > self.max_gap_us for _, _, t, _ in c.values()):
                c.clear()                           # not the base the others moved to: start over
            start, first, prev, n = c.get(kind, (t_us, t_us, t_us, 0))
            if t_us - prev > SOLE_STEP_US:
                first = t_us                        # not one stream's run of samples: its span starts again
            c[kind] = (start, first, max(prev, t_us), n + 1)   # one out of order or sent again breaks no run
            # every kind heard agrees on it; a stream of one kind alone, with two samples; or one kind's
            # samples alone over SOLE_SPAN_US (any other kind heard in between would have cleared them
            # or joined them): the other has fallen silent
            sole = len(c) == 1 and n + 1 >= 2 and max(prev, t_us) - first >= SOLE_SPAN_US
            if (set(c) >= self.heard and (len(self.heard) > 1 or n + 1 >= 2)) or sole:
                self.sole = (kind, start) if sole and len(self.heard) > 1 else None
                # the samples held while the base waited to be confirmed were its first, not wild stamps
                held = sum(v[3] for v in c.values()) - 1
                self.skipped["time_off_base"] -= held
                if self.skipped["time_off_base"] <= 0:
                    del self.skipped["time_off_base"]
                if held:
                    self.skipped["new_base_held"] += held
                return "rebase"
            self.skipped["time_off_base"] += 1
            return "drop"
        self.candidate.clear()                      # back on the base: what was held was a wild stamp
        if last is not None and t_us <= last:
            self.skipped[f"{kind}_out_of_order" if t_us < last else f"{kind}_resent"] += 1
            return "drop"
        self.last[kind] = t_us
        return "take"

    def unconfirmed(self) -> int:
        """How many samples are held for a base not yet confirmed as runs of a stream (two or more of one
        kind; a lone one is a wild stamp): at the end of a log, a new base it ended before confirming."""
        return sum(n for _, _, _, n in self.candidate.values() if n >= 2)

    def on_imu_clock(self, t_us: int) -> bool:
        """Whether a sample at t_us is where the IMU's latest sample taken is (within CONFIRM_US): a fix
        after a GNSS silence on GNSS alone, the IMU having kept the clock, and not a lone wild stamp."""
        imu = self.last.get("imu")
        return imu is not None and abs(t_us - imu) <= CONFIRM_US
