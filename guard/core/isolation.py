"""Which sensor an alarm names: the heading's witnesses.

Three sources see the heading turn: the gyro, the magnetometer and, on a ground vehicle at speed,
the GNSS course. `Witnesses` keeps the last 2 WITNESS_S of the magnetometer's heading (with the yaw
rate of each fusion), of the GNSS course (its residual against the filter's track and heading) and,
on wheels, of the lateral specific force, yaw rate and forward speed of every IMU fusion, and from
them names the sensor of a heading alarm (magnetometer, GNSS velocity):
- the magnetometer and the course turned alike, the gyro differently from both: the gyro bent the heading;
- the gyro and the magnetometer alike, the course apart: a GNSS velocity (a spoof) pulled it;
- the magnetometer apart from both, or its heading less the gyro's jumping (a bias bends, it cannot
  step): the magnetometer; neither: the magnetometer, with the gyro as a suspect (a noisy course);
- a GNSS velocity whose course agrees with the filter's heading but not with its track (the heading
  turned by the filter's own sideways velocity): the lateral accelerometer; on wheels only it pushes
  the track sideways.
- the accelerometer's "lateral" channel (on wheels, the sideways constraint's innovation): the gyro
  where the heading's witnesses say it bent the heading (the track then leaves the wheels' line
  too); the GNSS velocity where its course has left the filter's heading (a spoof drags the track
  sideways); else the accelerometer, which builds a sideways velocity the wheels do not have; with
  the GNSS velocity as a suspect where no course was at hand (standing still, a silent receiver),
  and the gyro too without a compass (the course is then held against the gyro's heading alone).
- a GNSS velocity alarm whose run began more than 2 WITNESS_S before it, its innovation across the
  track and the magnetometer still in use: the same turns over the whole run (up to RUN_S), the
  gyro's with the filter's bias of the run's onset; the magnetometer apart from the gyro and the
  course, they alike: the magnetometer. A compass turned slowly is learnt as the gyro's bias and the
  heading follows it, until the course alarms the GNSS velocity.
Without the course (in the air, standing still) a magnetometer alarm cannot be told from a gyro
bias, and an along-track GNSS velocity alarm never can be told from an accelerometer bias (a
coordinated spoof looks the same): the alarm names both.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import numpy as np

from guard.core.ekf import KS, LA, TH, VX, VY, W, FilterConfig
from guard.core.history import REWIND_S, keep_since
from guard.model.samples import GnssFix
from guard.model.sensors import AMBIGUOUS, CHANNELS, Sensor

WITNESS_S = 1.0        # s of course residuals weighed when a heading alarm is isolated; turns compared over 2x
WITNESS_Z = 2.0        # a witness disagrees with the filter when its mean residual is this many standard errors
JUMP_Z2 = 9.0          # a jump tells better than a drift by this many heading variances (3 sigma)
TURN_Z = (3.0, 2.0)    # two heading sources turned differently beyond the first, alike within the second (z)
RUN_S = REWIND_S       # s: how far back a GNSS velocity alarm's run is weighed
GAP_S = 1.0            # s: a run's witnesses with a longer gap between two of them are not weighed


class HeadingWitness(NamedTuple):     # one magnetometer fusion
    t_us: int
    heading: float
    rate: float                       # yaw rate read by the gyro


class CourseWitness(NamedTuple):      # one GNSS velocity at speed (ground vehicles)
    r: float                          # course - (heading + the filter's sideways velocity's angle)
    sigma: float
    t_us: int
    course: float                     # the heading the course shows: the course less the sideways angle the
                                      # wheels allow (the sensors' swing ahead of the axle, the tyres' slip)
    speed: float
    r0: float                         # course - (heading + the angle of the sideways velocity the wheels allow)
    noise: float                      # the course's own noise (rad): the fix's velocity noise across its track
                                      # over its speed


def compass_less_gyro(mag, gyro_bias: float) -> tuple[np.ndarray, np.ndarray]:
    """(t, d) of magnetometer witnesses: their times (s from the first) and their heading less the
    gyro's, its yaw rate less gyro_bias integrated."""
    t, heading, rate = np.array(mag).T
    t = (t - t[0]) / 1e6
    return t, np.unwrap(heading) - np.cumsum((rate - gyro_bias) * np.diff(t, prepend=0.0))


class Witnesses:
    def __init__(self, f: FilterConfig, freeze_speed_mps: float):
        self.f = f
        self.min_speed = max(2.0 * freeze_speed_mps, 0.5)
        self.course: deque[CourseWitness] = deque()
        self.mag: deque[HeadingWitness] = deque()
        self.side: deque[tuple[int, float, float, float]] = deque()   # every IMU fusion on wheels, compass
                                                                        # or not: (t, yaw rate, a_y, v_x)
        self.course_run: deque[CourseWitness] = deque()     # the same over RUN_S: an alarm's whole run
        self.mag_run: deque[HeadingWitness] = deque()
        self.last_vel = (np.zeros(2), np.eye(2))   # the latest GNSS velocity innovation and its S
        self.turned = 0.0                           # how far the compass turned from the gyro over the last
                                                    # run that named it (rad, compass_turned)

    def add_side(self, t_us: int, rate: float, ay: float, vx: float) -> None:
        """One IMU fusion of a ground vehicle: what the lateral accelerometer read, for its offset."""
        self.side.append((t_us, rate, ay, vx))
        keep_since(self.side, t_us - 2 * WITNESS_S * 1e6 + 1)

    def add_heading(self, w: HeadingWitness) -> None:
        self.mag.append(w)
        keep_since(self.mag, w.t_us - 2 * WITNESS_S * 1e6 + 1)
        self.mag_run.append(w)
        keep_since(self.mag_run, w.t_us - RUN_S * 1e6)

    def add_course(self, fix: GnssFix, x: np.ndarray, P_heading: float, ground: bool, vel_sigma: float,
                   held: bool = False) -> None:
        """The GNSS course against the filter's heading x (ground vehicles, at speed); vel_sigma the
        fix's velocity noise across its track. A course the receiver held (`held`) is no witness of the
        heading: it is left out, the witnesses before it kept as long as they would have been."""
        speed = math.hypot(fix.vel_e_mps, fix.vel_n_mps)
        if not ground or speed < self.min_speed:
            self.course.clear()            # standing still (or nearly): no course to speak of
            self.course_run.clear()
            return
        t_us = fix.t_us - int(self.f.gnss_delay_s * 1e6)
        if held:
            keep_since(self.course, t_us - 2 * WITNESS_S * 1e6 + 1, at=2)
            keep_since(self.course_run, t_us - RUN_S * 1e6, at=2)
            return
        course = math.atan2(fix.vel_n_mps, fix.vel_e_mps)
        # against the heading and what the wheels allow alone: the sensors' swing ahead of the axle and
        # the tyres' slip, as the filter has learnt them (the constraint without the filter's own v_y)
        allowed = math.atan2(x[LA] * x[W] - x[KS] * x[W] * x[VX] * abs(x[VX]), x[VX])
        r0 = math.remainder(course - x[TH] - allowed, math.tau)
        r = math.remainder(course - x[TH] - math.atan2(x[VY], x[VX]), math.tau)    # against the filter's track
        self.course.append(CourseWitness(r, math.sqrt((vel_sigma / speed) ** 2 + P_heading), t_us,
                                         course - allowed, speed, r0, vel_sigma / speed))
        keep_since(self.course, self.course[-1].t_us - 2 * WITNESS_S * 1e6 + 1, at=2)
        self.course_run.append(self.course[-1])
        keep_since(self.course_run, self.course[-1].t_us - RUN_S * 1e6, at=2)

    def fresh(self, t_us: int) -> bool:
        """A lateral accelerometer's reading within the last second (on wheels)."""
        return bool(self.side) and t_us - self.side[-1][0] < 1e6

    def isolate(self, sensor: Sensor, now_us: int, gyro_bias: float, run: tuple[int, float] | None = None
                ) -> tuple[Sensor, tuple[Sensor, ...], str | None]:
        """Which sensor a heading alarm (magnetometer, GNSS velocity) names, what it cannot rule out,
        and the channel when it names another sensor. A GNSS velocity whose course is off the filter's
        track by TURN_Z[0] or more and nearer than that to its heading has been pushed sideways by the
        filter, not by the receiver: the lateral accelerometer (one boundary for both: "alike" within
        TURN_Z[1] missed 2 of the harness's 40 seeds of a sideways bias, on the course's noise alone,
        while its spoofs' courses lay 4.8 or more from the heading at their alarms). `run`: a GNSS
        velocity alarm's run, (its onset, the filter's gyro bias then), see compass_turned."""
        if sensor == Sensor.GNSS_VEL and run is not None and self.compass_turned(now_us, *run):
            return Sensor.MAG, (), None
        turns = self.turns(now_us, gyro_bias)
        if turns is None or turns[1] is None:
            return sensor, AMBIGUOUS.get(sensor, ()), None
        z_gm, z_gc, z_mc = turns
        if min(abs(z_gm), abs(z_gc)) >= TURN_Z[0] and abs(z_mc) < TURN_Z[1]:
            return Sensor.GYRO, (), None
        if sensor == Sensor.MAG and abs(z_gm) < TURN_Z[1] and min(abs(z_gc), abs(z_mc)) >= TURN_Z[0]:
            # the gyro and the magnetometer turned alike, the course away from both: a GNSS velocity
            # (a spoof) pulled the filter's heading off the magnetometer's; named on its worse axis
            r, S = self.last_vel
            return Sensor.GNSS_VEL, (), CHANNELS[Sensor.GNSS_VEL][int(np.argmax(np.abs(r) / np.sqrt(np.diagonal(S))))]
        if sensor == Sensor.MAG:
            # the magnetometer alone when it turned apart from the gyro and the course, they alike, or when
            # it jumped (a gyro's bias bends the heading, it cannot step it); else the gyro stays a suspect
            apart = abs(z_gm) >= TURN_Z[0] and abs(z_mc) >= TURN_Z[1] > abs(z_gc)
            alone = apart or self.jumped(gyro_bias)
            return Sensor.MAG, (() if alone else AMBIGUOUS[Sensor.MAG]), None
        last = [(w.r, w.sigma, w.r0) for w in self.course if w.t_us > self.course[-1].t_us - WITNESS_S * 1e6]
        n = len(last)
        r, s, r0 = np.mean(last, axis=0)
        z, z0 = abs(r / s) * math.sqrt(n), abs(r0 / s) * math.sqrt(n)
        if z >= TURN_Z[0] > z0:
            return Sensor.ACCEL, (), "y"
        return sensor, (() if z >= WITNESS_Z else AMBIGUOUS.get(sensor, ())), None

    def isolate_lateral(self, now_us: int, gyro_bias: float) -> tuple[Sensor, tuple[Sensor, ...], str | None]:
        """Which sensor an alarm on the accelerometer's "lateral" channel names (see the module's
        docstring), what it cannot rule out, and the channel."""
        turns = self.turns(now_us, gyro_bias)
        if turns is None:       # no compass: the heading the course is held against is the gyro's alone
            return Sensor.ACCEL, (Sensor.GNSS_VEL, Sensor.GYRO), "lateral"
        if turns[1] is not None:
            z_gm, z_gc, z_mc = turns
            if min(abs(z_gm), abs(z_gc)) >= TURN_Z[0] and abs(z_mc) < TURN_Z[1]:
                return Sensor.GYRO, (), None
        # the course over the last 2 WITNESS_S (a 1 Hz receiver's two fixes): a spoof has dragged it off the
        # heading by then, a sideways bias leaves it on it; without two fixes at speed, either
        last = [(w.r0, w.sigma) for w in self.course]
        if len(last) < 2:
            return Sensor.ACCEL, (Sensor.GNSS_VEL,), "lateral"
        r0, s = np.mean(last, axis=0)
        if abs(r0 / s) * math.sqrt(len(last)) >= TURN_Z[0]:
            r, S = self.last_vel
            return Sensor.GNSS_VEL, (), CHANNELS[Sensor.GNSS_VEL][int(np.argmax(np.abs(r) / np.sqrt(np.diagonal(S))))]
        return Sensor.ACCEL, (), "lateral"

    def compass_turned(self, now_us: int, onset_us: int, gyro_bias: float) -> bool:
        """Whether, over a GNSS velocity alarm's run, the magnetometer turned apart from the gyro and the
        course, they alike. A compass turned slowly (0.5 degree/s) is learnt by the filter as the gyro's
        bias and the heading follows it, until the GNSS velocity, turned off the course with it, alarms:
        over the last 2 WITNESS_S the compass turned too little to tell, over the run it is plain. The
        gyro's heading uses the filter's bias at the run's onset, from before it learnt the compass's
        turn. Both records must cover the run without a gap (a course cleared while standing still, a
        compass fallen silent), and the GNSS velocity's innovation must lie across the track, as a
        heading's error turns it, not along it. Sets `turned`, the compass's turn from the gyro over the run."""
        if now_us - onset_us <= 2 * WITNESS_S * 1e6:
            return False                            # the last 2 WITNESS_S say as much (turns)
        mag = [w for w in self.mag_run if w.t_us >= onset_us]
        course = [c for c in self.course_run if c.t_us >= onset_us]
        for t in ([w.t_us for w in mag], [c.t_us for c in course]):
            if len(t) < 3 or t[0] - onset_us > GAP_S * 1e6 or now_us - t[-1] > GAP_S * 1e6 or \
                    max(np.diff(t)) > GAP_S * 1e6:
                return False
        r, c = self.last_vel[0], course[-1].course
        if abs(r[1] * math.cos(c) - r[0] * math.sin(c)) < abs(r[0] * math.cos(c) + r[1] * math.sin(c)):
            return False                            # off along the track, not across it as a heading turns it
        turns = self.turns(now_us, gyro_bias, mag, course)
        if turns is None or turns[1] is None:
            return False
        z_gm, z_gc, z_mc = turns
        if not (abs(z_gm) >= TURN_Z[0] and abs(z_mc) >= TURN_Z[1] > abs(z_gc)):     # as `apart` in isolate
            return False
        t, d = compass_less_gyro(mag, gyro_bias)
        self.turned = float(np.polyfit(t, d, 1)[0] * t[-1])
        return True

    def turns(self, now_us: int, gyro_bias: float, mag: list[HeadingWitness] | None = None,
              course: list[CourseWitness] | None = None) -> tuple[float, float | None, float | None] | None:
        """How differently the heading sources turned over the last 2 WITNESS_S (or over the witnesses
        given), as z-scores of the slope of their differences: (gyro - magnetometer, gyro - course,
        magnetometer - course), the last two None without the course; None without the magnetometer.
        The gyro's heading is its yaw rate, less the filter's bias, integrated."""
        mag = self.mag if mag is None else mag
        course = self.course if course is None else course
        if not mag or now_us - mag[-1].t_us > 1e6 or mag[-1].t_us - mag[0].t_us < 0.97 * WITNESS_S * 1e6:
            return None                             # no magnetometer, for over a second, or not for long yet
        t, heading, rate = np.array(mag).T
        t0, t = t[0], (t - t[0]) / 1e6
        gyro = np.cumsum((rate - gyro_bias) * np.diff(t, prepend=0.0))

        def slope(tt, y, sigma):                   # least-squares slope and its standard error
            d = tt - tt.mean()
            return float(d @ y) / float(d @ d), sigma / math.sqrt(float(d @ d))
        s_gm, e_gm = slope(t, gyro - np.unwrap(heading), self.f.heading_sigma_rad)
        course = [(c.t_us, c.course, c.noise) for c in course if c.t_us >= t0]
        if len(course) < 3 or course[-1][0] - course[0][0] < 0.85 * WITNESS_S * 1e6:
            return s_gm / e_gm, None, None
        tc, course, noise = np.array(course).T
        tc = (tc - t0) / 1e6
        # each course as noisy as the noisiest in the window (the slowest, or the least sure, fix)
        s_gc, e_gc = slope(tc, np.interp(tc, t, gyro) - np.unwrap(course), float(noise.max()))
        return s_gm / e_gm, s_gc / e_gc, (s_gc - s_gm) / math.hypot(e_gm, e_gc)

    def jumped(self, gyro_bias: float) -> bool:
        """Whether the magnetometer's heading less the gyro's, over the last 2 WITNESS_S, is told better
        by one jump (two levels) than by a drift (a line): a step in the magnetometer, not a gyro bias."""
        t, d = compass_less_gyro(self.mag, gyro_bias)
        if len(d) < 4:
            return False
        line = np.polyval(np.polyfit(t, d, 1), t)
        rss_line = float(np.sum((d - line) ** 2))
        total = np.cumsum(d)
        squares = np.cumsum(d * d)
        n = len(d)
        j = np.arange(1, n)
        left = squares[j - 1] - total[j - 1] ** 2 / j
        right = (squares[-1] - squares[j - 1]) - (total[-1] - total[j - 1]) ** 2 / (n - j)
        # by more than chance: the best of n - 1 splits beats a line on noise alone by a few sigma^2
        return rss_line - float(np.min(left + right)) > JUMP_Z2 * self.f.heading_sigma_rad ** 2

    def lateral_bias(self, gyro_bias: float, window_s: float = 2 * WITNESS_S, ahead: float = 0.0) -> float:
        """The lateral accelerometer's offset over the last window_s (2 s at most): its mean reading less
        the centripetal acceleration of a wheel that does not slide, yaw rate (less the filter's gyro
        bias) x speed, and less what the sensors `ahead` of the axle feel as the yaw rate changes
        (ahead x the yaw acceleration: over the window, ahead x the yaw rate's change / its length)."""
        t, rate, ay, vx = np.array([w for w in self.side if w[0] >= self.side[-1][0] - window_s * 1e6]).T
        span = (t[-1] - t[0]) / 1e6
        swing = ahead * (rate[-1] - rate[0]) / span if span > 0 else 0.0
        return float(np.mean(ay - (rate - gyro_bias) * vx)) - swing

    def gyro_bias(self) -> float:
        """The gyro's offset from the magnetometer: mean yaw rate minus the slope of the heading (last 2 s)."""
        t, heading, rate = np.array(self.mag).T
        return float(np.mean(rate) - np.polyfit((t - t[0]) / 1e6, np.unwrap(heading), 1)[0])
