"""A log's clock, checked against its receiver's: by the GNSS time its fixes carry, or where a log
carries none (a tlog), by the receiver's own motion and epochs.

An autopilot's clock keeps time to 50 ppm; some do not. `gnss_time_clock` fits the log's boot time
against the GNSS time every fix carries (a DataFlash GPS row's week and milliseconds, a ULog's
time_utc_usec) as a line over the whole log: parted by more than CLOCK_TOLERANCE in a straight line,
the time stamps are put on the receiver's time and that is said; a GNSS time that jumps (a receiver
restarting, or a spoofer moving it) is not a line, and corrects nothing. A line that holds three
quarters of the fixes is one, the rest left out and counted, if each of them lags it by at most
CLOCK_LAG_MAX_S (`stray_line`: fixes whose GNSS time was not yet updated, or that were read late).

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

Where the vehicle does not go that far, the receiver's epochs still show the clock (`epoch_rate`): a
receiver computes its fixes at a standard rate on GNSS time (5 Hz: every 200 ms exactly), and an
autopilot stamps each as it reads it. The Erle copters' rows came 180 or 200 ms apart on their 20 ms
loop, 184.6 ms on average: a 200 ms receiver read by a clock 8.3 % slow, as their GNSS time says
(1.083). Taken only where the intervals between fixes are a receiver's (at least MIN_INTERVALS, most
within 30 % of their median, their spread under EPOCH_SPREAD: not a telemetry stream's sampling of
them), their mean within EPOCH_REACH of a standard rate and off it by more than EPOCH_TOLERANCE. A
receiver set to an odd rate that close to a standard one (5.5 Hz) would be taken for a slow clock:
none was seen. Every Pixhawk log here: 0.9997 to 1.0001 (the PX4 ones are too short to judge).
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
CLOCK_LIMIT = 0.2           # beyond 20 % the time stamps are not a clock at all: said, not corrected
# against the GNSS time (gnss_time_clock)
CLOCK_TOLERANCE = 0.002     # a crystal is within 50 ppm: 0.2 % apart is a clock that is not keeping time
CLOCK_MIN_S = 30.0          # GNSS time over at least this long before the rate is judged
CLOCK_JITTER_S = 0.05       # the fit's rms residual: more, and the two clocks do not run in a line
CLOCK_STRAY_S = 0.1         # s off the line: a fix whose GNSS time lags it (not yet updated, or read late)
CLOCK_INLIERS = 0.75        # the share of the fixes a line must hold, the strays left out, to be a clock
CLOCK_LAG_MAX_S = 5.0       # s: a stray's GNSS time is behind the line by at most this (an Erle log's: 3.1)
# the receiver's epochs (guard.sources.clock.epoch_rate)
EPOCHS_MS = (100.0, 125.0, 200.0, 250.0, 500.0, 1000.0)    # the navigation rates autopilots set: 10 to 1 Hz
MIN_INTERVALS = 200
EPOCH_SHARE = 0.8           # of the intervals within 30 % of their median (the rest: missed epochs)
EPOCH_SPREAD = 0.08         # their spread, at most, against their mean (a loop's 20 ms steps: 5 %)
EPOCH_REACH = 0.105         # the standard rate the mean is nearest, within this (a 9 Hz receiver, 11 % off
                            # 10 Hz, is not taken for a 10 Hz one read by a slow clock)
EPOCH_TOLERANCE = 0.02      # a rate within 2 % of 1 is left alone


def motion_rate(fixes) -> tuple[float, float, int] | None:
    """(rate, standard error, stretches) of the log's clock against the receiver's motion, from
    fixes (t_us, lat, lon, v_n, v_e) in time order; None: too few stretches."""
    frame, prev, start, wins = None, None, None, []
    se = sn = path = 0.0
    for t, lat, lon, vn, ve in fixes:
        if vn is None:                      # a fix without a velocity ends a stretch
            prev = None
            continue
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


def epoch_rate(times) -> tuple[float, float, int, float] | None:
    """(rate, standard error, intervals, the standard interval in ms) of the log's clock against its
    receiver's epochs, from the times (us) of its fixes; None: the intervals are not a receiver's
    (too few, too scattered, or no standard rate near them)."""
    t = sorted(set(times))
    d = [(b - a) / 1e3 for a, b in zip(t, t[1:]) if 0 < b - a <= GAP_S * 1e6]
    if len(d) < MIN_INTERVALS:
        return None
    mid = statistics.median(d)
    core = [x for x in d if 0.7 * mid <= x <= 1.3 * mid]      # a missed epoch is not an interval
    if len(core) < EPOCH_SHARE * len(d):
        return None
    mean, sd = statistics.fmean(core), statistics.stdev(core)
    if sd > EPOCH_SPREAD * mean:
        return None
    standard = min(EPOCHS_MS, key=lambda s: abs(mean / s - 1.0))
    if abs(mean / standard - 1.0) > EPOCH_REACH:
        return None
    return standard / mean, standard * sd / (mean * mean * math.sqrt(len(core))), len(core), standard


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


def epoch_clock(times, notes: list[str]) -> tuple[int, float] | None:
    """(0, rate) from the receiver's epochs (see the module's docstring); None: as logged. What it
    finds is said in `notes`."""
    fit = epoch_rate(times)
    if fit is None:
        return None
    rate, se, n, standard = fit
    off = abs(rate - 1.0)
    if off <= EPOCH_TOLERANCE or off <= 3.0 * se:
        return None
    notes.append(f"the autopilot's clock ran {off * 100:.1f} % {'slow' if rate > 1.0 else 'fast'} against its "
                 f"receiver's epochs ({n} fixes {standard / rate:.1f} ms apart by it, a {standard:g} ms "
                 f"receiver's): every time stamp scaled by {rate:.4f}")
    return 0, rate


def gnss_time_clock(boot: list[float], gps: list[float], notes: list[str]) -> tuple[int, float] | None:
    """(t0, rate) from the boot times (s) of the fixes and the GNSS times (s) they carry: t0 the first
    fix's boot time (us); None: as logged. What it finds is said in `notes`."""
    if len(boot) < 20 or boot[-1] - boot[0] < CLOCK_MIN_S:
        return None
    b0, g0 = boot[0], gps[0]
    x = [b - b0 for b in boot]
    y = [g - g0 for g in gps]
    line = _line(x, y)
    if line is None:
        return None
    rate, c = line
    rms = math.sqrt(statistics.fmean([(b - c - rate * a) ** 2 for a, b in zip(x, y)]))
    strays = 0
    if rms > CLOCK_JITTER_S:        # a line through most of them, the fixes whose GNSS time lags left out?
        held = stray_line(x, y)
        if held is not None:
            rate, rms, strays = held
    if abs(rate - 1.0) <= CLOCK_TOLERANCE:
        return None
    said = (f"the autopilot's clock ran {abs(rate - 1.0) * 100:.1f} % {'slow' if rate > 1.0 else 'fast'} "
            "against the GNSS receiver's")
    if rms > CLOCK_JITTER_S or abs(rate - 1.0) > CLOCK_LIMIT:
        notes.append(f"{said}, not in a straight line (rms {rms:.2f} s) or beyond {CLOCK_LIMIT:.0%}: "
                     "time stamps left as logged")
        return None
    left = (f" ({strays} of its {len(x)} fixes left out, their GNSS time over {CLOCK_STRAY_S:g} s off the "
            "line: not yet updated, or read late)") if strays else ""
    notes.append(f"{said} over {boot[-1] - b0:.0f} s{left}: every time stamp scaled by {rate:.4f}")
    return int(b0 * 1e6), rate


def _line(x: list[float], y: list[float]) -> tuple[float, float] | None:
    """(rate, c) of the least-squares line y = c + rate x; None where every x is the same."""
    mx, my = statistics.fmean(x), statistics.fmean(y)
    sxx = sum((a - mx) ** 2 for a in x)
    if sxx <= 0.0:
        return None
    rate = sum((a - mx) * (b - my) for a, b in zip(x, y)) / sxx
    return rate, my - rate * mx


def stray_line(x: list[float], y: list[float]) -> tuple[float, float, int] | None:
    """(rate, rms, strays) of the line y = c + rate x that holds at least CLOCK_INLIERS of the points
    within CLOCK_STRAY_S, fitted to those alone; None where none does. A fix's GNSS time may lag its
    position: a driver that takes the time from one of the receiver's messages and the position from
    another logs the last time it had when the first is missed, and a busy loop reads a fix late. A
    few points then sit well under the line, which a least-squares fit through all of them reads as
    jitter. The Erle copters of 2014: half of each flight's fixes within 0.01 s of a line 8.3 % slow
    (the same in every quarter of each flight), and 9 to 23 % of them an epoch (0.2 s) to 3.1 s
    behind it, none ahead, their position fresh where their time repeats the fix before. Started
    from the median of the slopes between points half the log apart (a pair is off if either of its
    points strays: the median holds while under 29 % of them do, more than CLOCK_INLIERS lets
    through), then refitted on the points within CLOCK_STRAY_S until that set holds still. Strays
    are lags: a point ahead of the line by more than CLOCK_STRAY_S, or behind it by more than
    CLOCK_LAG_MAX_S, is a GNSS time that jumped (a receiver restarting, or a spoofer moving it), and
    then there is no clock, wherever in the log the jump comes; so too under CLOCK_INLIERS."""
    n, h = len(x), len(x) // 2
    slopes = sorted((y[k + h] - y[k]) / (x[k + h] - x[k]) for k in range(n - h) if x[k + h] > x[k])
    if not slopes:
        return None
    rate = slopes[len(slopes) // 2]
    c = statistics.median(b - rate * a for a, b in zip(x, y))
    kept: list[int] = []
    for _ in range(10):
        near = [k for k in range(n) if abs(y[k] - c - rate * x[k]) <= CLOCK_STRAY_S]
        if len(near) < CLOCK_INLIERS * n:
            return None
        if near == kept:
            break
        kept = near
        line = _line([x[k] for k in kept], [y[k] for k in kept])
        if line is None:
            return None
        rate, c = line
    else:
        return None                 # the set never held still: no line holds these fixes
    off = [y[k] - c - rate * x[k] for k in range(n)]
    if any(e > CLOCK_STRAY_S or e < -CLOCK_LAG_MAX_S for e in off):
        return None                 # a GNSS time ahead of the line, or far behind it: one that jumped
    rms = math.sqrt(statistics.fmean([off[k] ** 2 for k in kept]))
    return rate, rms, n - len(kept)
