"""Whether a receiver holds its course over ground at low speed, and how far a held course is off.

    python tools/course_hold.py FOLDER_OR_LOG [...] [--jobs 2] [--json out.json]

A receiver sends its speed and, apart, its course over ground (GPS_RAW_INT's vel and cog, DataFlash's
Spd and GCrs). Below a speed of its own, where a course means nothing, it keeps sending its last one,
and the velocity built from the two then points the wrong way (guard.core.aiding.gnss,
HELD_COURSE_MAX_MPS). Per log, as guard reads it (`guard replay`'s sources): the share of fixes, by
speed, whose course repeats the previous fix's to the last digit (its position not: that is a frozen
fix), and, at 0.5 to 3 m/s, the median
distance between the fix's velocity and the track its positions draw (their central difference over
SPAN_S either side), for held courses and for fresh ones. A receiver that sends its velocity as
north and east components (ULog, DroneCAN) repeats its course only where it came from a receiver's
speed and course (PX4 logs an NMEA receiver's so). A log whose clock goes back (a reboot) is read on,
its fixes after the reboot as a stretch of their own.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from guard.core.aiding.gnss import SAME_COURSE_RAD   # noqa: E402
from guard.core.geo import LocalFrame                # noqa: E402
from guard.errors import GuardError                  # noqa: E402
from guard.model.samples import GnssFix              # noqa: E402
from guard.runtime.replay import replay              # noqa: E402
from real_logs import each_log                       # noqa: E402 (beside this file)

BINS = (0.0, 0.3, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, math.inf)     # speed bins (m/s)
SPAN_S = 1.0            # the track's velocity: the positions at least this long before and after
MAX_SPAN_S = 6.0        # ... no further apart than this (a gap)
SLOW = (0.5, 3.0)       # the speeds at which a held course and a fresh one are compared (m/s)


class Fixes:
    """A replay's listener: every fix with a velocity, in order."""

    def __init__(self):
        self.rows: list[tuple[float, float, float, float, float]] = []    # t s, lat, lon, v_e, v_n
        self.shift = 0.0        # s added to the time stamps after a reboot, so that they go on rising

    def on_sample(self, sample) -> None:
        if isinstance(sample, GnssFix) and sample.fix_ok and sample.vel_n_mps is not None:
            t = sample.t_us * 1e-6 + self.shift
            if self.rows and t < self.rows[-1][0]:      # a reboot: a gap no track is drawn across
                self.shift += self.rows[-1][0] - t + 2 * MAX_SPAN_S
                t = sample.t_us * 1e-6 + self.shift
            if not self.rows or t > self.rows[-1][0]:
                self.rows.append((t, sample.lat_deg, sample.lon_deg, sample.vel_e_mps, sample.vel_n_mps))

    def on_events(self, events) -> None:
        pass

    def close(self) -> None:
        pass


def survey(rows: list[tuple]) -> dict:
    """The shares held by speed bin, and the velocity against the track, held and fresh."""
    a = np.array(rows, dtype=float)
    t, ve, vn = a[:, 0], a[:, 3], a[:, 4]
    speed = np.hypot(ve, vn)
    course = np.arctan2(ve, vn)
    held = np.zeros(len(a), dtype=bool)
    moved = (a[1:, 1] != a[:-1, 1]) | (a[1:, 2] != a[:-1, 2])          # a position repeated too: a frozen fix
    same = np.abs(course[1:] - course[:-1]) < SAME_COURSE_RAD
    held[1:] = (speed[1:] > 0.0) & (speed[:-1] > 0.0) & same & moved
    frame = LocalFrame(a[0, 1], a[0, 2], 0.0)
    en = np.array([frame.to_en(la, lo) for la, lo in a[:, 1:3]])
    bins = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        inside = (speed >= lo) & (speed < hi)
        bins.append({"from_mps": lo, "to_mps": hi, "fixes": int(inside.sum()), "held": int((held & inside).sum())})
    off: dict[bool, list[float]] = {True: [], False: []}
    before = np.searchsorted(t, t - SPAN_S, side="right") - 1         # the last fix SPAN_S or more before
    after = np.searchsorted(t, t + SPAN_S, side="left")              # the first SPAN_S or more after
    for i in np.flatnonzero((speed > SLOW[0]) & (speed < SLOW[1]) & (before >= 0) & (after < len(a))):
        j0, j1 = before[i], after[i]
        dt = t[j1] - t[j0]
        if dt > MAX_SPAN_S:
            continue
        track = (en[j1] - en[j0]) / dt
        off[bool(held[i])].append(float(math.hypot(ve[i] - track[0], vn[i] - track[1])))
    median = {k: (round(float(np.median(v)), 2) if v else None) for k, v in off.items()}
    return {"fixes": len(a), "bins": bins, "held_off_mps": median[True], "held_n": len(off[True]),
            "fresh_off_mps": median[False], "fresh_n": len(off[False])}


def course_of(path: str) -> dict:
    """One log's survey, as a JSON-ready dict (an "error" where it has none)."""
    fixes = Fixes()
    try:
        replay(path, listeners=[fixes])
    except GuardError as e:
        return {"log": path, "error": str(e)}
    except Exception as e:                  # noqa: BLE001 - one unreadable log is named, the others still run
        return {"log": path, "error": f"{type(e).__name__}: {e}"}
    if len(fixes.rows) < 3:
        return {"log": path, "error": f"{len(fixes.rows)} fixes with a velocity, too few"}
    return {"log": path, **survey(fixes.rows)}


def line(r: dict) -> str:
    """One log's line: the held share of each speed bin with fixes, and the velocity against the track."""
    shares = " ".join(f"{b['from_mps']:g}-{b['to_mps']:g} {b['held']}/{b['fixes']}" for b in r["bins"] if b["fixes"])
    held = (f"held {r['held_off_mps']:.2f} m/s off the track ({r['held_n']})" if r["held_n"]
            else "no held course")
    fresh = f"fresh {r['fresh_off_mps']:.2f} ({r['fresh_n']})" if r["fresh_n"] else "no fresh course"
    return (f"{Path(r['log']).name}: {r['fixes']} fixes; course repeated by speed (m/s) {shares}; at "
            f"{SLOW[0]:g}-{SLOW[1]:g} m/s {held}, {fresh}")


def main(argv=None) -> int:
    def show(r: dict) -> None:
        print(f"{Path(r['log']).name}: skipped: {r['error']}" if "error" in r else line(r))
    results = each_log(__doc__, course_of, show, argv)
    if isinstance(results, int):
        return results
    return 0 if any("error" not in r for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
