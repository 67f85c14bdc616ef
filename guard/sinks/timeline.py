"""What the core said, in the order it said it: each alarm, clearance and WARNING as a line with the
sample's time, for the summary `guard replay` prints (the report's lists hold them apart, and a
reboot's time goes back, so they cannot be put in order again from it)."""

from __future__ import annotations

from guard.model.events import UNITS, Alarm, Cleared, Notice
from guard.sinks.base import Sink

LINES = 20      # kept whole; the rest counted


class Timeline(Sink):
    def __init__(self):
        self.lines: list[str] = []
        self.more = 0

    def on_events(self, events) -> None:
        for e in events:
            if isinstance(e, Alarm):
                text = (f"ALARM {'|'.join((e.sensor, *e.ambiguous_with))} {e.channel} {e.offset:+.3g} "
                        f"{UNITS[e.sensor]} (GNSS sample {e.gnss_index}{': its alarm stands, again' if e.standing else ''})")
            elif isinstance(e, Cleared):
                text = f"clear {e.sensor} {e.channel} (GNSS sample {e.gnss_index})"
            elif isinstance(e, Notice) and e.level == "warning":
                text = f"WARNING {e.text}"
            else:
                continue
            if len(self.lines) < LINES:
                self.lines.append(f"{e.t_us / 1e6:9.1f} s  {text}")
            else:
                self.more += 1

    def said(self) -> list[str]:
        """The lines, then how many more there were."""
        tail = [f"... and {self.more} more alarms, clearances and warnings (--report has them all)"] if self.more else []
        return self.lines + tail
