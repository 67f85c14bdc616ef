"""A period of the samples' own time, for the sinks that check something now and then (the compass's
fit, the accelerometers' wander): on a log replayed at any speed, and across a reboot, a check comes
after as much of the vehicle's time as it would live."""

from __future__ import annotations


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
