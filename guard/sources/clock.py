"""A log's clock, checked against its receiver's own motion, where the log carries no GNSS time.

A tlog's GPS_RAW_INT has no GPS week or time of week: only the autopilot's boot clock stamps it. An
autopilot whose clock does not keep time (the Erle PXF's Linux autopilot of 2014 ran 8 to 10 %
slow: see guard.sources.dataflash.survey.clock_rate, which checks a DataFlash log against the GPS
time every fix carries) stamps every interval short, and a vehicle that flies far shows it: its
positions move further than its own velocities, integrated over the stamped time, say they should.

    over stretches of WINDOW_S of consecutive fixes (none more than GAP_S apart), each covering at
    least MIN_PATH_M:  displacement y_i = p(end) - p(start),  x_i = integral of v dt (trapezoid)
    rate = sum(x_i . y_i) / sum(x_i . x_i),  its standard error from the spread of x_i.y_i / x_i.x_i

Long stretches, because a receiver's position wanders by a metre and lags its velocity by a fix:
against 50 m, that is 2 %; between consecutive fixes it is everything (hovering copters gave rates of
0.76 to 1.21 that way, and ArduPilot's SITL 0.94). A rate is taken only from MIN_WINDOWS stretches,
off by more than MOTION_TOLERANCE and by three standard errors, with a standard error under
MAX_SE; a hovering copter never covers 50 m in 10 s and is left as logged. On the real flights that
do (two Erle planes): 1.079 and 1.089, as their DataFlash logs' GNSS time says (1.079 and 1.087).
On the simulator's clean 10-minute drives, whose clock keeps time (6 seeds of the defaults and 6
vehicles of the second family): 0.996 to 1.001, a quarter of the tolerance at most.
"""

from __future__ import annotations

import math
import statistics

from guard.core.geo import LocalFrame

WINDOW_S = 10.0         # s: one stretch of the track
GAP_S = 1.5             # s: fixes further apart end a stretch
MIN_PATH_M = 50.0       # m the vehicle covers in a stretch, for it to count
MIN_WINDOWS = 5
MOTION_TOLERANCE = 0.02     # a rate within 2 % of 1 is left alone (a receiver's lag and wander)
MAX_SE = 0.01
CLOCK_LIMIT = 0.2           # beyond 20 % the time stamps are not a clock at all


def motion_rate(fixes) -> tuple[float, float, int] | None:
    """(rate, standard error, stretches) of the log's clock against the receiver's motion, from
    fixes (t_us, lat, lon, v_n, v_e) in time order; None: too few stretches."""
    frame, prev, start, wins = None, None, None, []
    se = sn = path = 0.0
    for t, lat, lon, vn, ve in fixes:
        frame = frame or LocalFrame(lat, lon, 0.0)
        e, n = frame.to_en(lat, lon)
        if prev is None or not 0 < t - prev[0] <= GAP_S * 1e6:
            start, se, sn, path = (t, e, n), 0.0, 0.0, 0.0
        else:
            dt = (t - prev[0]) / 1e6
            se += 0.5 * (ve + prev[4]) * dt
            sn += 0.5 * (vn + prev[3]) * dt
            path += 0.5 * (math.hypot(ve, vn) + math.hypot(prev[4], prev[3])) * dt
            if t - start[0] >= WINDOW_S * 1e6:
                if path >= MIN_PATH_M:
                    wins.append((se, sn, e - start[1], n - start[2]))
                start, se, sn, path = (t, e, n), 0.0, 0.0, 0.0
        prev = (t, e, n, vn, ve)
    if len(wins) < MIN_WINDOWS:
        return None
    xx = sum(a * a + b * b for a, b, _, _ in wins)
    rate = sum(a * c + b * d for a, b, c, d in wins) / xx
    each = [(a * c + b * d) / (a * a + b * b) for a, b, c, d in wins]
    return rate, statistics.stdev(each) / math.sqrt(len(each)), len(wins)


def motion_clock(fixes, notes: list[str]) -> tuple[int, float] | None:
    """(t0, rate) to put a log's time stamps on its receiver's time, t0 + (t - t0) rate, t0 its first
    fix's time; None: as logged. What it finds is said in `notes`."""
    fixes = list(fixes)
    fit = motion_rate(fixes)
    if fit is None:
        return None
    rate, se, n = fit
    off = abs(rate - 1.0)
    if off <= MOTION_TOLERANCE or off <= 3.0 * se or se > MAX_SE:
        return None
    said = (f"the autopilot's clock ran {off * 100:.1f} % {'slow' if rate > 1.0 else 'fast'} against its "
            f"receiver's own motion (positions against velocities over {n} stretches of {WINDOW_S:g} s)")
    if off > CLOCK_LIMIT:
        notes.append(f"{said}: beyond {CLOCK_LIMIT:.0%}, time stamps left as logged")
        return None
    notes.append(f"{said}: every time stamp scaled by {rate:.4f}")
    return fixes[0][0], rate
