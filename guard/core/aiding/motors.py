"""The motors' start and stop, and what they do to the compass.

A compass sits among the motors' and the battery's wires, and their current is a field in the body:
at rest it reads within a degree of the heading, and as the motors spin up and the vehicle lifts off
it is turned by a few to tens of degrees, then by about as much for as long as the current holds
(ArduPilot's compassmot calibration measures it per ampere, and its EKF resets its yaw and its
field states once the vehicle is in the air, for what it met on the ground). On the real flights of
the README the compass read within 0.8 degrees of guard's heading before the motors and 5 to 39
degrees off in the first seconds after lift-off, and 10 of the 51 magnetometer alarms came within
10 s of the motors' start (`python tools/real_logs.py FOLDERS`: those flights before and after this).

The motors are heard in the IMU: their vibration is the accelerometers' short noise
(guard.core.aiding.imu.ImuNoise.vibration: the median of the last few second differences), which a
motor start lifts from the still IMU's hundredths of a m/s^2 to tenths or more within a sample or
two. `MotorWatch` smooths it over SMOOTH_S and says "start" when it passes both VIB_FLOOR and RISE
times its still level (learnt while still, over STILL_TAU_S), and "stop" when it has been back under
half that for STOP_S. An IMU that vibrates from its first sample (a log begun in flight, a noisy IMU)
has no start, and no still level to draw its stop's line from: the line is then its running level
(smoothed over RUN_TAU_S) over RISE, as a start's is the still level times RISE, held between
VIB_FLOOR / 2 and VIB_FLOOR (a still IMU reads up to 0.07 m/s^2, over a fixed VIB_FLOOR / 2; a
running motor never reads under VIB_FLOOR).

From each start or stop, for OPEN_S, the compass's offset b_psi is a faster random walk (Q_OPEN,
its variance capped at P_OPEN_MAX), so that the offset the current turns the compass by is learnt
as an offset, the heading held by the gyro (guard.core.monitor), and how far it turned is said when the
window closes (a WARNING from MOTORS_SAY_DEG: a compassmot calibration's work; beyond CURRENT_MAX_DEG, more
than a current does, said as such: a real copter's hard flight that the 2D model could not hold
turned its learnt offset 101 degrees in one window). A fast change of the compass (a
step of tens of degrees within a fusion) still alarms; one laid in over seconds is learnt.

What it costs: an attacker who turns the compass slowly within OPEN_S of a motor start or stop
is taken for the current and not reported (guard's own heading stays on the gyro, and the GNSS
course still witnesses it); an attacker who writes a vibration into the accelerometers to open the
window is heard as a motor start, on a vehicle whose motors already run, only if the IMU was still
before. The simulator's IMU never starts its motors: its figures do not move.
"""

from __future__ import annotations

import math

from guard.core.ekf import BM
from guard.model.events import Notice

VIB_FLOOR = 0.1         # m/s^2, the least vibration that is motors (a still IMU: 0.005 to 0.07)
RISE = 4.0              # ... and this many times the still level
SMOOTH_S = 0.2          # s, the level's own smoothing (one median of a few samples jitters by half)
STILL_TAU_S = 2.0       # s, the memory of the still level
STOP_S = 2.0            # s under half the start's line: the motors stopped
RUN_TAU_S = 10.0        # s, the memory of the running level (a stop's line where no still level was heard)
OPEN_S = 20.0           # s from a start or stop during which the compass's offset moves fast (lift-off
                        # within 10 s of the motors' start on the real flights, hover within 10 s more)
Q_OPEN = 0.2            # rad/sqrt(s), its random walk then (11 degrees in a second)
P_OPEN_MAX = 0.5 ** 2   # rad^2, the most its variance grows to then (29 degrees, 1 sigma)
MOTORS_SAY_DEG = 10.0   # degrees the compass turned in the window that are a WARNING (less: INFO)
CURRENT_MAX_DEG = 45.0  # degrees beyond which a turn is more than the motors' current makes (the real
                        # flights: 5 to 39), and is said as what else it may be


class MotorWatch:
    def __init__(self):
        self.level: float | None = None     # the vibration, smoothed over SMOOTH_S (its mean square's root)
        self.still: float | None = None     # the still IMU's level (m/s^2)
        self.running: bool | None = None    # None until the first level is heard
        self.run: float | None = None       # the running level, where the IMU vibrated from its first sample
        self.opened_us: int | None = None   # the last start's or stop's time
        self._ms = 0.0
        self._t_us: int | None = None
        self._under_since: int | None = None
        self._window: tuple | None = None   # the last start's or stop's word, its filter and b_psi then
        self.moved = 0.0                    # rad, what b_psi moved in the closed windows (of one filter each)

    def step(self, t_us: int, level: float | None, ekf) -> list[Notice]:
        """One IMU sample's vibration level, with the filter (None before the first fix): a start or a
        stop said (INFO), and when its window closes how far the compass's offset moved in it (a
        WARNING from MOTORS_SAY_DEG, INFO under it; not said if the filter started again in it)."""
        moved = self.add(t_us, level)
        if moved is not None:
            what = "started" if moved == "start" else "stopped"
            self._window = (what, ekf, None if ekf is None else float(ekf.x[BM]))
            return [Notice(t_us, "info", f"the motors {what} (the IMU's vibration): the compass's offset is learnt "
                           f"anew for {OPEN_S:g} s, as their current turns it")]
        if self._window is None:
            return []
        what, ekf0, b0 = self._window
        if ekf0 is None and ekf is not None:
            self._window = (what, ekf, float(ekf.x[BM]))        # the first fix came in the window
            return []
        if self.open(t_us):
            return []
        self._window = None
        if ekf0 is None or ekf0 is not ekf:
            return []
        self.moved += math.remainder(float(ekf.x[BM]) - b0, math.tau)
        turn = -math.degrees(math.remainder(float(ekf.x[BM]) - b0, math.tau))     # clockwise, as a compass reads
        big = abs(turn) >= MOTORS_SAY_DEG
        why = "" if not big else (": their current's field; a compassmot calibration takes it out"
                                  if abs(turn) <= CURRENT_MAX_DEG else
                                  f": more than a motors' current turns a compass (up to about {CURRENT_MAX_DEG:g} "
                                  "deg): a compass that failed or was attacked, or a manoeuvre the filter's heading "
                                  "could not follow (in the window the compass held the heading little)")
        return [Notice(t_us, "warning" if big else "info", f"the compass turned {turn:+.1f} deg in the {OPEN_S:g} s "
                       f"after the motors {what} (learnt as its offset)" + why)]

    def add(self, t_us: int, level: float | None) -> str | None:
        """One IMU sample's vibration level (None while unknown): "start", "stop" or None."""
        if level is None:
            return None
        last, self._t_us = self._t_us, t_us
        if self.running is None:
            self._ms, self.running = level * level, level >= VIB_FLOOR
            self.still = None if self.running else level
            self.run = level if self.running else None
            return None
        dt = max(0, t_us - last) / 1e6
        self._ms += min(1.0, dt / SMOOTH_S) * (level * level - self._ms)
        self.level = now = self._ms ** 0.5
        line = max(VIB_FLOOR, RISE * (self.still or 0.0))
        if not self.running:
            if now < line:
                self.still += min(1.0, dt / STILL_TAU_S) * (now - self.still)
                return None
            self.running, self.opened_us = True, t_us
            return "start"
        # begun running, no still level heard: the line from the running level, learnt while over it
        stop = 0.5 * line if self.still is not None else min(max(self.run / RISE, 0.5 * VIB_FLOOR), VIB_FLOOR)
        if now >= stop:
            if self.still is None:
                self.run += min(1.0, dt / RUN_TAU_S) * (now - self.run)
            self._under_since = None
            return None
        if self._under_since is None:
            self._under_since = t_us
        if t_us - self._under_since < STOP_S * 1e6:
            return None
        self.running, self.still, self.run, self.opened_us, self._under_since = False, now, None, t_us, None
        return "stop"

    def still_offset(self, ekf) -> float | None:
        """The compass's offset with the motors still: the filter's b_psi less what it moved in the
        windows, the one still open included (what `guard tune` writes: a flight's take-off is learnt
        anew in its own window, and a profile that started b_psi at an in-flight offset would count
        the motors' turn twice). None without a filter."""
        if ekf is None:
            return None
        b = float(ekf.x[BM])
        if self._window is not None and self._window[1] is ekf:
            b -= math.remainder(b - self._window[2], math.tau)
        return math.remainder(b - self.moved, math.tau)

    def open(self, t_us: int) -> bool:
        """Whether the compass's offset moves fast at t_us (within OPEN_S of a start or stop)."""
        return self.opened_us is not None and 0 <= t_us - self.opened_us < OPEN_S * 1e6


def offset_q(q_config: float, open_: bool, p_offset: float) -> float:
    """The compass offset's random walk (rad/sqrt(s)): the configured one, or Q_OPEN while the window is
    open and its variance under P_OPEN_MAX; never where the configuration learns no offset (0)."""
    if q_config > 0.0 and open_ and p_offset < P_OPEN_MAX:
        return max(q_config, Q_OPEN)
    return q_config
