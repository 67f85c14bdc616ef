"""The pump: the one loop that feeds samples to the core and its events to the sinks.

The daemon (a sample at a time, as the link gives them), replay, the evaluation harness and the
benchmarks (a whole log) all run through it, so that a sample reaches the core and the sinks the
same way everywhere. A sink that raises is logged and counted (`sink_errors`), and dropped from the
rest of the run only if it keeps failing: estimation never stops for a sink.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Iterable

from guard.core.monitor import Monitor
from guard.model.events import Event
from guard.sinks.base import Sink

log = logging.getLogger(__name__)
MAX_SINK_ERRORS = 100       # a sink that failed this often is taken out of the run


class Pump:
    def __init__(self, monitor: Monitor, sinks: Iterable[Sink] = ()):
        self.monitor = monitor
        self.sinks: list[Sink] = list(sinks)
        self.samples = 0
        self.sink_errors: Counter[str] = Counter()

    def feed(self, sample) -> list[Event]:
        """One sample through the core; its events to every sink. Returns the events."""
        self.samples += 1
        events = self.monitor.step(sample)
        for sink in tuple(self.sinks):
            self._deliver(sink, sample, events)
        return events

    def finish(self) -> list[Event]:
        """At the end of a stream: what the core still owed, to the sinks."""
        events = self.monitor.finish()
        for sink in tuple(self.sinks):
            self._deliver(sink, None, events)
        return events

    def run(self, samples: Iterable, every: int = 0, tick: Callable[[], None] | None = None) -> None:
        """Every sample of `samples`, then finish(); `tick()` every `every` samples (a progress bar)."""
        for i, sample in enumerate(samples):
            self.feed(sample)
            if tick is not None and every and i % every == 0:
                tick()
        self.finish()

    def _deliver(self, sink: Sink, sample, events: list[Event]) -> None:
        try:
            if sample is not None:
                sink.on_sample(sample)
            if events:
                sink.on_events(events)
        except Exception as e:          # noqa: BLE001 - a sink's failure must never stop estimation
            name = type(sink).__name__
            self.sink_errors[name] += 1
            if self.sink_errors[name] == 1:
                log.error("%s failed (%s: %s): estimation goes on", name, type(e).__name__, e)
            if self.sink_errors[name] >= MAX_SINK_ERRORS:
                log.error("%s failed %d times: taken out of this run", name, self.sink_errors[name])
                self.sinks.remove(sink)
