"""A period of the samples' own time, for the sinks that check something now and then (the compass's
fit, the accelerometers' wander, the receiver's), and the live side those sinks share in guard run.

On a log replayed at any speed, and across a reboot, a check comes after as much of the vehicle's time
as it would live.
"""

from __future__ import annotations

from collections.abc import Callable


class Every:
    """`due(t_us)` is True once every period_s of sample time: the first sample starts the period, and a
    clock gone back by more than a period (a reboot) starts it again."""

    def __init__(self, period_s: float):
        self.period_us = period_s * 1e6
        self._next_us: float | None = None

    def due(self, t_us: int) -> bool:
        if self._next_us is None or t_us < self._next_us - self.period_us:     # the first, or a clock gone back
            self._next_us = t_us + self.period_us
            return False
        if t_us >= self._next_us:
            self._next_us = t_us + self.period_us
            return True
        return False


class Live:
    """The live side of a measuring sink (mixed in before it: `class LiveWander(Live, Agreement)`, its
    `__init__` calling `live` first thing): it listens until `done`, checks every `period_s` of the
    samples' time on the samples `ticks` accepts, and says its line once (`tell`, a WARNING on the link
    and in the log), after which it lets go of what it held (`let_go`) and listens no more. `said_us`:
    when it spoke, on the samples' clock."""

    def live(self, say: Callable[[str], None], period_s: float) -> None:
        self.say = say
        self.done = False
        self.said_us: int | None = None
        self._every = Every(period_s)

    def on_sample(self, s) -> None:
        if self.done:
            return
        super().on_sample(s)
        if self.ticks(s) and self._every.due(s.t_us):
            self.check(s.t_us)

    def on_events(self, events) -> None:
        if not self.done:
            super().on_events(events)

    def ticks(self, s) -> bool:
        """Whether this sample may start a check (one of the stream the sink measures)."""
        return True

    def check(self, t_us: int) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        """Listen no more, holding nothing."""
        self.done = True
        self.let_go()

    def let_go(self) -> None:
        raise NotImplementedError

    def tell(self, t_us: int, line: str) -> None:
        """Say `line` once, whatever `say` does."""
        self.said_us = t_us
        self.stop()
        self.say(line)
