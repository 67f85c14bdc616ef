"""What a receiver usually says of itself: how far its accuracy figures are taken.

A fix's noise is the receiver's own accuracy figures (h_acc, vel_acc: guard.core.aiding.gnss), bounded
above, because a receiver, or a spoofer, that suddenly claims a huge error would blind every test. A
bound fixed at ACC_CAP times the floors (0.6 m/s, a position good to 8.75 m) is wrong for a receiver
that is that poor all along: a real PX4 octocopter's, with 7 to 11 satellites, called its velocity
good to 1.1 to 2.8 m/s for whole flights (PX4's own filter fused it in one flight and refused it in
another), and tested at 0.6 m/s its honest noise raised 14 GNSS velocity alarms in 2.5 minutes of flight
(README, "A receiver that knows it is poor").

So the bound is the larger of the fixed one and LEVEL_FACTOR times the receiver's usual figure: the
median of what it reported over the last LEVEL_WINDOW_S of fixes heard while every test was calm
(nothing near its threshold, nothing set aside), and never more than LEVEL_MAX times the floors. The
filter's first fixes (nothing tested yet) count, so a receiver that is poor from power-on is taken at
its word from the start (a restarted filter's do not while an alarm stands through the restart).
What it costs, and what it does not:
- a receiver good to 0.1 m/s that suddenly claims 3 m/s (a spoofer blinding the tests) is still taken
  at the fixed bound: its usual figure is 0.1, and a claim that lasts is heard only while no test
  stirs, for more than half the window before the median moves;
- a spoofer who raises the claimed error slowly, before he moves anything, raises the bound with it,
  up to LEVEL_MAX times the floors; the monitor says so (a WARNING once the bound passes the fixed
  one), so that an operator whose receiver is good hears of it. On a vehicle that `guard tune` has
  seen, the usual figure is believed only up to USUAL_MARGIN times the worst its clean logs showed
  (`gnss_h_acc_usual_max_m`, `gnss_vel_acc_usual_max_mps`, written by tune: `UsualWorst`): a
  receiver good to 0.1 m/s in every clean flight is never taken at more than the fixed bound,
  however slowly its claims creep up, and a usual figure past that is said (a WARNING) instead;
- a receiver that is poor is tested as poor: its attacks must be that much larger to be seen, and
  the WARNING says so.

This file learns the figure; GnssAiding applies it and the monitor feeds it.
"""

from __future__ import annotations

from bisect import bisect_left, insort
from collections import deque

from guard.model.samples import GnssFix

LEVEL_WINDOW_S = 120.0  # s of calm fixes whose median is the receiver's usual figure
LEVEL_FACTOR = 1.5      # a fix's figure is taken up to this many times the usual (real receivers' reports
                        # vary by 1.25 at the 90th percentile, 1.55 at most, about their median in a flight)
LEVEL_MAX = 50.0        # ... and never beyond this many times the floor (3 m/s; a position good to 44 m)
USUAL_MARGIN = 2.0      # guard tune believes a usual figure up to this many times its clean logs' worst (a
                        # day with fewer satellites: the worst usual vel_acc of one vehicle's flights varied
                        # by up to 1.7 times between them on the README's real flights)
SETTLED_S = LEVEL_WINDOW_S / 2   # s of fixes a usual figure is taken over before it is compared with the
                                 # tuned most (a receiver settling after power-on reports metres at first)


class TimedMedian:
    """The median of the values heard over the last `window_s` (statistics.median's value, kept sorted
    as values come and go: a fix at 5 Hz would otherwise sort two minutes of them each time). A time
    that goes back (the autopilot rebooted) starts the window over."""

    def __init__(self, window_s: float):
        self.window_us = window_s * 1e6
        self.heard: deque[tuple[int, float]] = deque()   # (t_us, value), in time order
        self._sorted: list[float] = []

    def hear(self, t_us: int, value: float | None) -> None:
        """`value` heard at t_us (None or 0: nothing heard, the window still moves on)."""
        if self.heard and t_us < self.heard[-1][0]:
            self.heard.clear()
            self._sorted.clear()
        if value:
            self.heard.append((t_us, value))
            insort(self._sorted, value)
        while self.heard and self.heard[0][0] < t_us - self.window_us:
            del self._sorted[bisect_left(self._sorted, self.heard.popleft()[1])]

    def median(self) -> float | None:
        n = len(self._sorted)
        if not n:
            return None
        i = n // 2
        return self._sorted[i] if n % 2 else (self._sorted[i - 1] + self._sorted[i]) / 2

    def span_s(self) -> float:
        """The time between the first and the last value in the window."""
        return (self.heard[-1][0] - self.heard[0][0]) / 1e6 if self.heard else 0.0


class ReceiverLevel:
    """The medians of a receiver's reported h_acc and vel_acc over its last LEVEL_WINDOW_S of calm fixes:
    h_acc (m) and vel_acc (m/s), None where none was heard."""

    def __init__(self):
        self.h_window = TimedMedian(LEVEL_WINDOW_S)
        self.v_window = TimedMedian(LEVEL_WINDOW_S)
        self.h_acc: float | None = None
        self.vel_acc: float | None = None

    def hear(self, fix: GnssFix, calm: bool) -> None:
        """A fix the filter is about to use; its figures count towards the usual ones if calm. A time
        that goes back (the autopilot rebooted) starts the window over."""
        self.h_window.hear(fix.t_us, fix.h_acc_m if calm else None)
        self.v_window.hear(fix.t_us, fix.vel_acc_mps if calm else None)
        self.h_acc = self.h_window.median()
        self.vel_acc = self.v_window.median()

    def settled(self) -> tuple[bool, bool]:
        """Whether the h_acc and the vel_acc medians are each over at least SETTLED_S of fixes (a start,
        a reboot or a long gap starts the span over): a receiver still settling is no usual figure."""
        return tuple(bool(w.heard) and w.span_s() >= SETTLED_S for w in (self.h_window, self.v_window))


class UsualWorst:
    """The worst usual figures of a receiver over a log (guard tune): the largest of ReceiverLevel's
    medians once settled (its window over SETTLED_S of fixes: the first fixes of a receiver still
    settling, after a start, a reboot or a long gap, are no usual figure; the monitor compares its own
    usual figure with the tuned most by the same rule), or the log's last median where it never
    settled. h_acc (m), vel_acc (m/s), None where the receiver reported none."""

    def __init__(self):
        self.level = ReceiverLevel()
        self.h_acc: float | None = None
        self.vel_acc: float | None = None

    def hear(self, fix: GnssFix) -> None:
        if not fix.fix_ok:
            return
        self.level.hear(fix, True)
        h_settled, v_settled = self.level.settled()
        if h_settled:
            self.h_acc = _larger(self.h_acc, self.level.h_acc)
        if v_settled:
            self.vel_acc = _larger(self.vel_acc, self.level.vel_acc)

    def worst(self) -> tuple[float | None, float | None]:
        """(h_acc, vel_acc): the worst usual figures, or the last medians for a short log."""
        return (self.h_acc if self.h_acc is not None else self.level.h_acc,
                self.vel_acc if self.vel_acc is not None else self.level.vel_acc)


def _larger(a: float | None, b: float | None) -> float | None:
    return b if a is None else a if b is None else max(a, b)


def bound(floor: float, fixed: float, usual: float | None, usual_max: float = 0.0) -> float:
    """The largest noise a fix's own figure is taken at: the fixed bound, or LEVEL_FACTOR times the
    receiver's usual figure (already in noise units), whichever is larger, up to LEVEL_MAX floors.
    `usual_max` (noise units; 0: none), what a tuned vehicle's usual figure is believed up to."""
    if usual is None:
        return fixed
    return max(fixed, min(LEVEL_FACTOR * believed(usual, usual_max), LEVEL_MAX * floor))


def believed(usual: float, most: float) -> float:
    """A usual figure as far as it is believed: up to a tuned vehicle's most (0: no most)."""
    return min(usual, most) if most > 0.0 else usual
