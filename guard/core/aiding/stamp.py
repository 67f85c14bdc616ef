"""A fix whose position is a receiver epoch off its own time stamp, brought back to it.

An autopilot that streams its receiver's fixes slower than the receiver makes them (a 5 Hz receiver
sent at 2 Hz over telemetry) stamps each with the time it worked out for it, and now and then pairs a
position with the stamp of the epoch before or after: ArduPilot's GPS_RAW_INT.time_usec is the fix's
GPS time carried on by the time since the fix came in. Seen on a real QuadPlane's telemetry (the
README's 47 flights: tridge/cuav's flight.tlog, at 18 to 23 m/s, 8 of its 132 moving fixes 0.2 s
off their stamps, 3.4 to 4.4 m along the track, each the next fix back on its stamp), where such
fixes raised 4 GNSS position alarms.

The receiver's own data tell it apart from a step. Between two fixes it moved dp, and its own
velocity (the mean of the two, v) says that takes tau = dp.v / |v|^2 where the stamps say dt. A fix
is brought back to its stamp, p - v_fix delta with delta = tau - dt, where all of these hold:
  - the stream is thinned: its recent stamps' intervals differ by more than THINNED of their median
    (a stream with every fix in it, a DataFlash log's or the simulator's, is never touched);
  - |delta| is at most MAX_SLIP_S and under MAX_SLIP_SHARE of dt (a frozen fix, tau = 0, is never one);
  - the shift is real: |delta| |v| over SLIP_SIGMAS times the fix's position noise;
  - the fix lies on the track: its distance across it is within FIT_SIGMAS times that noise;
  - the fix before was not brought back itself.
The next fix is compared with the one brought back.

What it costs: a position step along the track of at most MAX_SLIP_S times the speed (4 m at 16 m/s)
and nothing across it, on a thinned stream, is taken at its first fix as a slip and tested from the
second (which, compared with the first brought back, shows the step and is not one itself). A fix
brought back lies on the receiver's own track: a spoofer who moves every other fix along it gains
no fix the filter takes off the track.
"""

from __future__ import annotations

import math
import statistics
from collections import deque

from guard.model.samples import GnssFix

MAX_SLIP_S = 0.25       # a slip is one epoch of a receiver of 4 Hz or faster, sent slower than it makes fixes
MAX_SLIP_SHARE = 0.75   # ... and less than the interval it slipped in: a frozen fix (tau = 0) is no slip
SLIP_SIGMAS = 3.0       # a shift under this many sigma of the fix's noise is left to the tests
FIT_SIGMAS = 1.0        # the fix's distance across the track, at most
THINNED = 0.25          # the intervals' spread over their median of a stream thinned from a faster receiver
INTERVALS = 10          # the recent intervals it is judged on
MAX_DT_S = 2.0          # two fixes further apart than this are not compared


class FixStamps:
    """Brings a fix back to its stamp where the receiver's own data say it slipped (the module's docstring)."""

    def __init__(self):
        self._last: tuple[int, float, float, float, float, bool] | None = None   # t, e, n, ve, vn, brought back
        self._intervals: deque[float] = deque(maxlen=INTERVALS)
        self.brought_back = 0

    def restart(self) -> None:
        """A new filter compares its first fix with nothing."""
        self._last = None
        self._intervals.clear()

    def _thinned(self) -> bool:
        if len(self._intervals) < INTERVALS:
            return False
        median = statistics.median(self._intervals)
        return median > 0.0 and (max(self._intervals) - min(self._intervals)) > THINNED * median

    def check(self, fix: GnssFix, en: tuple[float, float], sigma_m: float) -> tuple[float, float]:
        """The fix's (east, north), brought back to its stamp where it slipped, else `en` as it is."""
        last, self._last = self._last, None
        if fix.vel_n_mps is None or fix.vel_e_mps is None:
            return en
        out, slipped = en, False
        if last is not None and 0 < fix.t_us - last[0] <= MAX_DT_S * 1e6:
            dt = (fix.t_us - last[0]) / 1e6
            self._intervals.append(dt)
            ve, vn = (fix.vel_e_mps + last[3]) / 2.0, (fix.vel_n_mps + last[4]) / 2.0
            speed2 = ve * ve + vn * vn
            de, dn = en[0] - last[1], en[1] - last[2]
            if speed2 > 0.0 and not last[5] and self._thinned():
                speed = math.sqrt(speed2)
                delta = (de * ve + dn * vn) / speed2 - dt
                across = abs(de * vn - dn * ve) / speed
                if (abs(delta) <= min(MAX_SLIP_S, MAX_SLIP_SHARE * dt) and
                        abs(delta) * speed > SLIP_SIGMAS * sigma_m and across <= FIT_SIGMAS * sigma_m):
                    out = (en[0] - fix.vel_e_mps * delta, en[1] - fix.vel_n_mps * delta)
                    slipped = True
                    self.brought_back += 1
        self._last = (fix.t_us, out[0], out[1], fix.vel_e_mps, fix.vel_n_mps, slipped)
        return out
