"""The sink interface: a listener of the core's events (python-can's `Listener` is the model).

A sink is told every sample (`on_sample`, before the events it caused) and every list of events
the core returns (`on_events`), and is closed once at the end. It never calls back into the core.
"""

from __future__ import annotations


class Sink:
    def on_sample(self, sample) -> None:
        """A sample as the source gave it (most sinks ignore them)."""

    def on_events(self, events: list) -> None:
        """The events of one step of the core."""

    def close(self) -> None:
        """End of the run: flush, finish files."""
