"""The core: one object with one pure, synchronous step. Sample in, events out, no I/O.

Live MAVLink, tlog replay, the CAN path and the tests all run this same object.

Per IMU sample: level the IMU with the autopilot's roll and pitch (a flying drone is tilted),
predict the filter to the sample's time, form the innovations of heading, gyro and accelerometer,
test them, fuse them. Per GNSS sample: the same with position and velocity, then an Estimate. A
GNSS alarm rewinds the filter to before the attack (`_rewind`) at the next sample, once the alarm
is out; the alarm epoch's Estimate waits for it and comes out with that sample's events.
An IMU faster than `imu_fusion_hz` is averaged down to that rate first (as PX4's EKF2 does): the
mean of the samples since the last fusion is fused at the last one's time, which keeps a 250 Hz
IMU affordable on a companion computer. The noise model is left as configured (conservative).

A sensor whose test rejects H0 raises an Alarm and is then excluded: its innovations are still
formed and tested, but no longer fused, so the estimate rides on the other sensors instead of
following the attack. It is re-admitted (Cleared) when its normalised innovations have stayed
within `readmit_sigma` for `readmit_s` seconds (and READMIT_SAMPLES samples). GNSS position and
velocity come from one receiver and go together; a position is not re-admitted while its velocity
is still out (and tested: fixes without a velocity do not hold it). A gyro waits until
its heading turns with the magnetometer's again (its own innovation agrees as soon as it is out).

Which sensor an alarm names (`_isolate`): a heading alarm (magnetometer, GNSS velocity) compares
how three sources turned: the gyro, the magnetometer and, on a ground vehicle, the GNSS course; the
magnetometer and the course alike against the gyro means the gyro bent the heading; the gyro and the
magnetometer alike against the course, that a GNSS velocity (a spoof) pulled it. A GNSS velocity
alarm whose course agrees with the filter's heading but not with its track (the heading turned by
the filter's own sideways velocity) names the lateral accelerometer: on wheels only it pushes the
track sideways. A ground vehicle (`vehicle`, from the autopilot's HEARTBEAT by default) also has
v_y = 0 fused with every IMU update.
"""

from __future__ import annotations

import datetime
import math
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from .detectors import DetectorConfig, make_detector
from .ekf import (BAY, BW, H_IMU, H_IMU_GROUND, H_IMU_NO_MAG, H_IMU_NO_MAG_GROUND, H_POS, N_STATES, TH, VX, VY,
                  FilterConfig, NavEKF, gnss_velocity_model)
from .events import AMBIGUOUS, CHANNELS, Alarm, Cleared, Estimate, Event, Innovation, Notice, Tested
from .geo import LocalFrame, declination_rad
from .samples import Attitude, GnssFix, ImuSample, VehicleType

WITNESS_S = 1.0        # s of course residuals weighed when a heading alarm is isolated; turns compared over 2x
WITNESS_Z = 2.0        # a witness disagrees with the filter when its mean residual is this many standard errors
TURN_Z = (3.0, 2.0)    # two heading sources turned differently beyond the first, alike within the second (z)
RECEIVER = ("gnss_pos", "gnss_vel")                 # one receiver: excluded together
READMIT_SAMPLES = 10   # and at least this many samples in a row (a 1 Hz receiver: 10 s, not 3 samples)
REWIND_S = 20.0        # s of filter history kept to undo what a GNSS attack fed the filter before its alarm
# rows of the stacked IMU measurement that belong to each sensor: (sensor, first, last + 1)
IMU_BLOCKS = (("mag", 0, 1), ("gyro", 1, 2), ("accel", 2, 4))
IMU_BLOCKS_NO_MAG = (("gyro", 0, 1), ("accel", 1, 3))


def keep_since(history: deque, t_us: float, at: int = 0) -> None:
    """Drop the entries of a history of tuples whose time (item `at`) is older than t_us."""
    while history and history[0][at] < t_us:
        history.popleft()


def state_minus(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b for two filter states, the heading's difference wrapped to (-pi, pi]."""
    d = a - b
    d[TH] = math.remainder(d[TH], math.tau)
    return d


@dataclass(frozen=True)
class MonitorConfig:
    filter: FilterConfig = field(default_factory=FilterConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    exclude_on_alarm: bool = True
    readmit_sigma: float = 3.0
    readmit_s: float = 3.0
    declination_deg: float | None = None    # None: from the World Magnetic Model at the first fix
    max_gap_s: float = 10.0                 # a longer silence, or time running backwards, re-initialises
    imu_fusion_hz: float = 50.0             # a faster IMU is averaged down to this rate before fusion (0: off)
    freeze_speed_mps: float = 1.0           # a GNSS fix repeated to the last digit while faster than this is frozen
    vehicle: str = "auto"                   # "ground": v_y = 0 is fused; "air": not; "auto": from the HEARTBEAT


class Monitor:
    """Runs the EKF and the detector over a stream of samples.

    `record_tests`: emit a Tested event (innovation, statistic, threshold) for every fusion. Sinks
    that log or plot them need it; a bare replay does not, and skips the cost.
    `date`: when the data was recorded, for the magnetic declination (None: today, as live); a
    replay passes its log's, so that a log replays alike whatever the day.
    """

    def __init__(self, cfg: MonitorConfig | None = None, record_tests: bool = True,
                 date: datetime.date | None = None):
        self.cfg = cfg or MonitorConfig()
        self.record_tests = record_tests
        self.date = date
        n_channels = sum(len(c) for s, c in CHANNELS.items() if s != "gnss_vel" or self.cfg.filter.use_gnss_velocity)
        self.detector = make_detector(self.cfg.detector, n_channels)
        f = self.cfg.filter
        # R: measurement noise covariance of each measurement set
        self.R_pos = np.eye(2) * f.gnss_pos_sigma_m ** 2
        self.R_vel = np.eye(2) * f.gnss_vel_sigma_mps ** 2
        # IMU block (heading, gyro, accel x, y), and for a ground vehicle the sideways velocity after it;
        # indexed by `ground`
        sig = [f.heading_sigma_rad, f.gyro_sigma_radps, f.accel_sigma_mps2, f.accel_sigma_mps2, f.lateral_sigma_mps]
        self.R_imu = (np.diag(np.square(sig[:4])), np.diag(np.square(sig)))
        self.R_imu_no_mag = (self.R_imu[0][1:, 1:].copy(), self.R_imu[1][1:, 1:].copy())
        self.H_imu = (H_IMU, H_IMU_GROUND)
        self.H_imu_no_mag = (H_IMU_NO_MAG, H_IMU_NO_MAG_GROUND)
        self.ground = self.cfg.vehicle == "ground"
        self._receiver = RECEIVER if f.use_gnss_velocity else ("gnss_pos",)     # what one receiver's alarm excludes
        self.skipped: Counter[str] = Counter()
        self.gnss_index = -1
        self.roll = self.pitch = 0.0
        self._last_mag: tuple[float, float] | None = None     # levelled (m_x, m_y) of the latest IMU sample
        self._reset()

    def _reset(self) -> None:
        self.ekf: NavEKF | None = None
        self.frame: LocalFrame | None = None
        self.declination = 0.0
        self.t_us: int | None = None
        self.gnss_lost = False
        self.excluded: dict[str, int] = {}         # sensor -> time of the last inconsistent innovation
        self._agreed: Counter[str] = Counter()      # excluded sensor -> consistent samples since then
        self._with_receiver: set[str] = set()      # excluded with the receiver, not by an alarm of its own
        self._accel_ref: float | None = None        # a laterally biased accelerometer's bias before the attack
        self._last_vel = (np.zeros(2), np.eye(2))   # the latest GNSS velocity innovation and its S
        self.detector.reset()
        self._imu_sum = [0.0] * 5                   # ax, ay, yaw rate, m_x, m_y since the last fusion
        self._imu_n = self._mag_n = 0
        self._imu_t: int | None = None              # time of the last fused IMU measurement
        self._last_fix: tuple | None = None         # (lat, lon, v_n, v_e) of the previous fix
        self._last_fix_t: int | None = None         # and its time stamp
        self._vel_t = -math.inf                     # time of the last GNSS velocity tested
        # the heading sources over the last 2 WITNESS_S (by time: any GNSS or IMU rate): the GNSS course
        # (ground vehicles, at speed), (r, sigma) against the filter's heading and (t_us, course, speed);
        # the magnetometer, (t_us, heading, yaw rate)
        fuse_hz = self.cfg.imu_fusion_hz or 1000.0    # IMU fusions per second, at most
        self._course: deque = deque()
        self._mag: deque = deque()
        # the filter before each GNSS epoch's fusion, (t_us, x, P), over the last REWIND_S, and every
        # IMU fusion since the oldest of them, (t_us, z, H, R, angle_rows): what a rewind needs
        self._epochs: deque = deque()
        self._imu_log: deque = deque()
        # with a receiver latency: the filter's state after each IMU fusion, (t_us, x), back to the latency
        self._states: deque = deque(maxlen=int((self.cfg.filter.gnss_delay_s + 1.0) * fuse_hz) + 2)
        self._rewind_epochs = 0                     # a rewind owed: done at the next step, after the alarm is out
        self._estimate_owed: tuple[int, int] | None = None   # (t_us, gnss_index) of the alarm's epoch

    # -- the step -----------------------------------------------------------------------------
    def step(self, sample) -> list[Event]:
        if isinstance(sample, Attitude):
            self.roll, self.pitch = sample.roll_rad, sample.pitch_rad
            return []
        if isinstance(sample, VehicleType):
            return self._vehicle(sample)
        events = self.finish()                      # an alarm's rewind, then its epoch's Estimate, if owed
        if isinstance(sample, GnssFix):
            self.gnss_index += 1
        timed = not (isinstance(sample, GnssFix) and not sample.fix_ok)    # a no-fix message's time means nothing
        if timed and self.t_us is not None and (sample.t_us < self.t_us - 200_000
                                      or sample.t_us > self.t_us + self.cfg.max_gap_s * 1e6):
            jump = (sample.t_us - self.t_us) / 1e6
            events.append(Notice(sample.t_us, "warning", f"time jumped {jump:+.1f} s: filter re-initialised"))
            # a new filter fuses every sensor again: a ground station's latched alarms are cleared
            events += [Cleared(sample.t_us, self.gnss_index, s, c) for s in self.excluded
                       if s not in self._with_receiver for c in CHANNELS[s]]
            self._reset()
        if isinstance(sample, GnssFix):
            events += self._gnss(sample)
        elif isinstance(sample, ImuSample):
            events += self._imu(sample)
        return events

    def finish(self) -> list[Event]:
        """At the end of a stream: what the last step still owed (an alarm's rewind and its epoch's
        Estimate, which wait for the next sample)."""
        events: list[Event] = []
        if self._rewind_epochs:
            self._rewind(self._rewind_epochs)
            self._rewind_epochs = 0
        if self._estimate_owed:
            events.append(self._estimate(*self._estimate_owed))
            self._estimate_owed = None
        return events

    def _vehicle(self, v: VehicleType) -> list[Event]:
        if self.cfg.vehicle != "auto" or v.ground == self.ground:
            return []
        self.ground = v.ground
        what = ("a ground vehicle: its sideways velocity is held at zero" if v.ground
                else "a vehicle that may move sideways: sideways velocity left free")
        return [Notice(self.t_us or 0, "info", f"the autopilot reports {what}")]

    def _advance(self, t_us: int) -> None:
        if t_us > self.t_us:
            self.ekf.predict((t_us - self.t_us) / 1e6)
            self.t_us = t_us

    # -- GNSS -----------------------------------------------------------------------------------
    def _gnss(self, fix: GnssFix) -> list[Event]:
        events: list[Event] = []
        if not fix.fix_ok:
            self.skipped["gnss_no_fix"] += 1
            if not self.gnss_lost:
                self.gnss_lost = True
                events.append(Notice(fix.t_us, "warning", "GNSS fix lost: coasting on the IMU" if self.ekf
                                     else "GNSS without a fix: monitoring starts at the first fix"))
            return events
        if self.gnss_lost:
            self.gnss_lost = False
            events.append(Notice(fix.t_us, "info", "GNSS fix back" if self.ekf else "GNSS fix: monitoring starts"))
        if fix.t_us == self._last_fix_t:             # the same message again (a resend): nothing new
            self.skipped["gnss_resent"] += 1
            return events
        self._last_fix_t = fix.t_us
        if self.ekf is None:
            return events + self._initialise(fix)
        self._advance(fix.t_us)
        ekf = self.ekf
        # the state's own time, which a fix stamped before the last IMU sample is not: the rewind
        # re-runs the IMU fusions after it, and only those
        self._epochs.append((self.t_us, ekf.x.copy(), ekf.P.copy()))
        keep_since(self._epochs, self.t_us - REWIND_S * 1e6)
        events += self._freeze(fix)
        delayed = self.cfg.filter.gnss_delay_s > 0
        xd = self._delayed(fix.t_us) if delayed else ekf.x     # the state the fix shows
        before = ekf.x.copy() if delayed else None
        e, n = self.frame.to_en(fix.lat_deg, fix.lon_deg)
        events += self._measure("gnss_pos", fix.t_us, np.array([e, n]), xd[:2].copy(), H_POS, self.R_pos)
        if delayed:                 # the position's correction, carried to the state the velocity is tested on
            xd = xd + state_minus(ekf.x, before)
        if self.cfg.filter.use_gnss_velocity and fix.vel_n_mps is not None:
            self._witness_course(fix, xd)
            hx, H = gnss_velocity_model(xd)
            events += self._measure("gnss_vel", fix.t_us, np.array([fix.vel_e_mps, fix.vel_n_mps]), hx, H,
                                    self.R_vel)
        if delayed:                 # the correction applies to the stored states too: the next fix sees it
            dx = state_minus(ekf.x, before)
            for _, x in self._states:
                x += dx
        if self._rewind_epochs:     # this epoch raised an alarm that rewinds: its estimate comes after that
            self._estimate_owed = (fix.t_us, self.gnss_index)
        else:
            events.append(self._estimate(fix.t_us, self.gnss_index))
        return events

    def _estimate(self, t_us: int, gnss_index: int) -> Estimate:
        x, f = self.ekf.x, self.frame
        return Estimate(t_us, gnss_index, float(x[0]), float(x[1]), float(x[TH]), x.copy(),
                        np.diagonal(self.ekf.P).copy(), (f.lat0, f.lon0, f.alt0))

    def _delayed(self, t_us: int) -> np.ndarray:
        """The filter's state gnss_delay_s before t_us, interpolated between the stored IMU-fusion states
        (the current state last). The innovation is formed against it and the correction applied to
        the current state with the current P (a delayed fix's usual approximation)."""
        then = t_us - self.cfg.filter.gnss_delay_s * 1e6
        states = self._states
        while len(states) > 1 and states[1][0] <= then:
            states.popleft()
        pts = [*states, (self.t_us, self.ekf.x)]
        for (t0, x0), (t1, x1) in zip(pts, pts[1:]):
            if t0 <= then < t1:
                return x0 + state_minus(x1, x0) * ((then - t0) / (t1 - t0))
        return pts[0][1].copy()     # older than the history (the first fixes): the oldest state there is

    def _witness_course(self, fix: GnssFix, x: np.ndarray) -> None:
        """The GNSS course against the filter's heading x (ground vehicles, at speed): a witness of the heading."""
        speed = math.hypot(fix.vel_e_mps, fix.vel_n_mps)
        if not self.ground or speed < max(2.0 * self.cfg.freeze_speed_mps, 0.5):
            self._course.clear()            # standing still (or nearly): no course to speak of
            return
        course = math.atan2(fix.vel_n_mps, fix.vel_e_mps)
        r0 = math.remainder(course - x[TH], math.tau)          # against the heading alone
        r = math.remainder(r0 - math.atan2(x[VY], x[VX]), math.tau)    # against the filter's track
        self._course.append((r, math.sqrt((self.cfg.filter.gnss_vel_sigma_mps / speed) ** 2 + self.ekf.P[TH, TH]),
                             fix.t_us - int(self.cfg.filter.gnss_delay_s * 1e6), course, speed, r0))
        keep_since(self._course, self._course[-1][2] - 2 * WITNESS_S * 1e6 + 1, at=2)

    def _isolate(self, sensor: str) -> tuple[str, tuple[str, ...], str | None]:
        """Which sensor a heading alarm (magnetometer, GNSS velocity) names, what it cannot rule out,
        and the channel when it names another sensor.

        Three sources see the heading turn: the gyro, the magnetometer and, on a ground vehicle at
        speed, the GNSS course. When the magnetometer and the course turned alike over the last
        2 WITNESS_S and the gyro turned differently from both, the gyro is named. A GNSS velocity
        whose course is off the filter's track (heading plus its own sideways velocity) by TURN_Z[0]
        or more and nearer than that to its heading has been pushed sideways by the filter, not by
        the receiver: a wheel does not slide, so the lateral accelerometer is named (one boundary for
        both: "alike" within TURN_Z[1] missed 2 of the harness's 40 seeds of a sideways bias, on the
        course's noise alone, while its spoofs' courses lay 4.8 or more from the heading at their
        alarms). Otherwise the alarmed sensor is named; a GNSS velocity alone when its course
        disagrees with the filter's track. Without the course (in the air, standing still) a
        magnetometer alarm cannot be told from a gyro bias, and an along-track GNSS velocity alarm
        never can be told from an accelerometer bias (a coordinated spoof looks the same): the alarm
        names both.
        """
        turns = self._turns()
        if turns is None or turns[1] is None:
            return sensor, AMBIGUOUS.get(sensor, ()), None
        z_gm, z_gc, z_mc = turns
        if min(abs(z_gm), abs(z_gc)) >= TURN_Z[0] and abs(z_mc) < TURN_Z[1]:
            return "gyro", (), None
        if sensor == "mag" and abs(z_gm) < TURN_Z[1] and min(abs(z_gc), abs(z_mc)) >= TURN_Z[0]:
            # the gyro and the magnetometer turned alike, the course away from both: a GNSS velocity
            # (a spoof) pulled the filter's heading off the magnetometer's; named on its worse axis
            r, S = self._last_vel
            return "gnss_vel", (), CHANNELS["gnss_vel"][int(np.argmax(np.abs(r) / np.sqrt(np.diagonal(S))))]
        if sensor == "mag":
            return "mag", (), None
        last = [(w[0], w[1], w[5]) for w in self._course if w[2] > self._course[-1][2] - WITNESS_S * 1e6]
        n = len(last)
        r, s, r0 = np.mean(last, axis=0)
        z, z0 = abs(r / s) * math.sqrt(n), abs(r0 / s) * math.sqrt(n)
        if z >= TURN_Z[0] > z0:
            return "accel", (), "y"
        return sensor, (() if z >= WITNESS_Z else AMBIGUOUS.get(sensor, ())), None

    def _turns(self) -> tuple[float, float | None, float | None] | None:
        """How differently the heading sources turned over the last 2 WITNESS_S, as z-scores of the
        slope of their differences: (gyro - magnetometer, gyro - course, magnetometer - course), the
        last two None without the course; None without the magnetometer. The gyro's heading is its
        yaw rate, less the filter's bias, integrated."""
        if not self._mag or self.t_us - self._mag[-1][0] > 1e6 or \
                self._mag[-1][0] - self._mag[0][0] < 0.97 * WITNESS_S * 1e6:
            return None                             # no magnetometer, for over a second, or not for long yet
        t, heading, rate = np.array(self._mag)[:, :3].T
        t0, t = t[0], (t - t[0]) / 1e6
        gyro = np.cumsum((rate - self.ekf.x[BW]) * np.diff(t, prepend=0.0))

        def slope(tt, y, sigma):                   # least-squares slope and its standard error
            d = tt - tt.mean()
            return float(d @ y) / float(d @ d), sigma / math.sqrt(float(d @ d))
        f = self.cfg.filter
        s_gm, e_gm = slope(t, gyro - np.unwrap(heading), f.heading_sigma_rad)
        course = [c[2:5] for c in self._course if c[2] >= t0]
        if len(course) < 3 or course[-1][0] - course[0][0] < 0.85 * WITNESS_S * 1e6:
            return s_gm / e_gm, None, None
        tc, course, speed = np.array(course).T
        tc = (tc - t0) / 1e6
        s_gc, e_gc = slope(tc, np.interp(tc, t, gyro) - np.unwrap(course), f.gnss_vel_sigma_mps / speed.min())
        return s_gm / e_gm, s_gc / e_gc, (s_gc - s_gm) / math.hypot(e_gm, e_gc)

    def _rewind(self, epochs: int) -> None:
        """Undo the last `epochs` GNSS epochs: back to the filter before the attack's first sample was
        fused (a position's CUSUM run gives the onset; a velocity goes back as far as the history
        does), then the IMU fusions since, GNSS left out. Up to REWIND_S of IMU (tens of
        milliseconds), so it runs at the step after the alarm's, once the alarm is out."""
        epochs = min(epochs, len(self._epochs))     # a run longer than the history: as far back as it goes
        if epochs < 1:
            return
        t0, x, P = self._epochs[-epochs]
        now, ekf = self.t_us, self.ekf
        delayed, states = self.cfg.filter.gnss_delay_s > 0, [(t0, x.copy())]   # with a receiver latency: re-run states
        # the bias states come back with the rest: a velocity alarm goes back as far as the history does,
        # before a spoof the filter took for an accelerometer bias could have fed them; a position's
        # run start is its onset. (Not the oldest epoch's for every rewind: in the filter's first 20 s
        # those are start-up guesses, and coasting on them keeps a GNSS that agrees again out.)
        ekf.x, ekf.P, t = x.copy(), P.copy(), t0
        for t_imu, z, H, R, angle in self._imu_log:
            if t_imu <= t0:
                continue
            ekf.predict((t_imu - t) / 1e6)
            t = t_imu
            r, S, PHT = ekf.innovation(z, H @ ekf.x, H, R, angle_rows=angle)
            ekf.fuse(r, S, H, R, PHT)
            if delayed:
                states.append((t_imu, ekf.x.copy()))
        ekf.predict((now - t) / 1e6)
        self._epochs.clear()
        self._imu_log.clear()
        if delayed:                 # the states before t0 stand; those after it are the re-run's
            kept = [st for st in self._states if st[0] < t0]
            self._states.clear()
            self._states.extend(kept + states)

    def _readmit(self, sensor: str, t_us: int) -> list[Event]:
        del self.excluded[sensor]
        self._agreed.pop(sensor, None)
        if sensor == "accel":
            self._accel_ref = None
        self.detector.forget(sensor)                # a fresh test: what it summed while excluded is spent
        if sensor in self._with_receiver:           # it raised no alarm: nothing to clear on a ground station
            self._with_receiver.discard(sensor)
            return []
        return [Cleared(t_us, self.gnss_index, sensor, c) for c in CHANNELS[sensor]]

    def _lateral_bias(self) -> float:
        """The lateral accelerometer's offset over the last 2 s: its mean reading less the centripetal
        acceleration of a wheel that does not slide, yaw rate (less the filter's gyro bias) x speed."""
        _, _, rate, ay, vx = np.array(self._mag).T
        return float(np.mean(ay - (rate - self.ekf.x[BW]) * vx))

    def _gyro_bias(self) -> float:
        """The gyro's offset from the magnetometer: mean yaw rate minus the slope of the heading (last 2 s)."""
        t, heading, rate = np.array(self._mag)[:, :3].T
        return float(np.mean(rate) - np.polyfit((t - t[0]) / 1e6, np.unwrap(heading), 1)[0])

    def _freeze(self, fix: GnssFix) -> list[Event]:
        """A receiver's noise never repeats a fix to the last digit while the vehicle moves: a repeat
        at speed is a frozen (replayed or stuck) GNSS. Both its position and velocity are excluded."""
        key = (fix.lat_deg, fix.lon_deg, fix.vel_n_mps, fix.vel_e_mps)
        repeated, self._last_fix = key == self._last_fix, key
        speed = math.hypot(self.ekf.x[VX], self.ekf.x[VY])
        if not repeated or speed < self.cfg.freeze_speed_mps or "gnss_pos" in self.excluded:
            return []
        if self.cfg.exclude_on_alarm:
            for out in self._receiver:
                if out not in self.excluded and out != "gnss_pos":
                    self._with_receiver.add(out)    # excluded with it, no alarm of its own to clear
                self.excluded[out] = fix.t_us
                self._agreed.pop(out, None)
        return [Alarm(fix.t_us, self.gnss_index, "gnss_pos", "frozen", speed, self.cfg.freeze_speed_mps, 0.0,
                      "freeze")]

    def _initialise(self, fix: GnssFix) -> list[Event]:
        self.frame = LocalFrame(fix.lat_deg, fix.lon_deg, fix.alt_m)
        dec = self.cfg.declination_deg
        self.declination = (declination_rad(fix.lat_deg, fix.lon_deg, fix.alt_m, self.date) if dec is None
                            else math.radians(dec))
        x0 = np.zeros(N_STATES)
        ve, vn = fix.vel_e_mps or 0.0, fix.vel_n_mps or 0.0
        if self._last_mag is not None:
            heading = self._heading(*self._last_mag)
        else:
            heading = math.atan2(vn, ve) if math.hypot(ve, vn) > 1.0 else 0.0
        x0[TH] = heading
        # body velocity from the ground velocity: v_body = R(theta)^T v_en
        x0[VX] = math.cos(heading) * ve + math.sin(heading) * vn
        x0[VY] = -math.sin(heading) * ve + math.cos(heading) * vn
        self.ekf = NavEKF(self.cfg.filter, x0)
        self.t_us = fix.t_us
        return [Notice(fix.t_us, "info", f"filter initialised at {fix.lat_deg:.6f}, {fix.lon_deg:.6f}")]

    # -- IMU ------------------------------------------------------------------------------------
    def _imu(self, s: ImuSample) -> list[Event]:
        ax, ay, rate, mag = self._level(s)
        self._last_mag = mag
        if self.ekf is None:
            self.skipped["imu_before_first_fix"] += 1
            return []
        # average a fast IMU down to imu_fusion_hz: the mean of n samples, fused at the last one's time
        acc = self._imu_sum
        acc[0] += ax; acc[1] += ay; acc[2] += rate
        self._imu_n += 1
        if mag is not None:
            acc[3] += mag[0]; acc[4] += mag[1]
            self._mag_n += 1
        hz = self.cfg.imu_fusion_hz
        if hz > 0 and self._imu_t is not None and s.t_us - self._imu_t < 0.9e6 / hz:
            return []
        n, nm = self._imu_n, self._mag_n
        ax, ay, rate = acc[0] / n, acc[1] / n, acc[2] / n
        mag = (acc[3] / nm, acc[4] / nm) if nm else None
        self._imu_sum, self._imu_n, self._mag_n, self._imu_t = [0.0] * 5, 0, 0, s.t_us
        self._advance(s.t_us)
        heading = None if mag is None else self._heading(*mag)
        g = self.ground
        if heading is None:
            self.skipped["imu_no_magnetometer"] += 1
            z, H, R, blocks = [rate, ax, ay], self.H_imu_no_mag[g], self.R_imu_no_mag[g], IMU_BLOCKS_NO_MAG
        else:
            z, H, R, blocks = [heading, rate, ax, ay], self.H_imu[g], self.R_imu[g].copy(), IMU_BLOCKS
            # a heading sampled up to heading_lag_s late is off by up to yaw rate * lag
            R[0, 0] += (rate * self.cfg.filter.heading_lag_s) ** 2
        if g:
            z.append(0.0)                          # the sideways velocity of a wheeled vehicle
        z = np.array(z)
        r, S, PHT = self.ekf.innovation(z, H @ self.ekf.x, H, R, angle_rows=(0,) if heading is not None else ())
        if heading is not None:
            self._mag.append((s.t_us, heading, rate, ay, self.ekf.x[VX]))
            keep_since(self._mag, s.t_us - 2 * WITNESS_S * 1e6 + 1)
        # one stacked update, tested sensor by sensor
        events: list[Event] = []
        keep: list[int] = []
        for sensor, i, j in blocks:
            ev, fused = self._test(sensor, s.t_us, r[i:j], S[i:j, i:j])
            events += ev
            if fused:
                keep.extend(range(i, j))
        if g:
            keep.append(len(r) - 1)                # a constraint, not a sensor: never tested, always fused
        angle = (0,) if heading is not None else ()
        if len(keep) == len(r):
            self.ekf.fuse(r, S, H, R, PHT)
            self._imu_log.append((s.t_us, z, H, R, angle))
        elif keep:
            ix = np.ix_(keep, keep)
            self.ekf.fuse(r[keep], S[ix], H[keep], R[ix], PHT[:, keep])
            self._imu_log.append((s.t_us, z[keep], H[keep], R[ix], angle if keep[0] == 0 else ()))
        # a rewind re-runs the fusions after its epoch: those before the oldest one kept are not needed
        keep_since(self._imu_log, self._epochs[0][0] if self._epochs else math.inf)
        if self.cfg.filter.gnss_delay_s > 0:
            self._states.append((s.t_us, self.ekf.x.copy()))
        return events

    def _heading(self, mx: float, my: float) -> float:
        """ENU yaw from the levelled field: compass chi = atan2(-m_y, m_x) + declination, theta = pi/2 - chi."""
        return math.remainder(math.pi / 2 - (math.atan2(-my, mx) + self.declination), math.tau)

    def _level(self, s: ImuSample):
        """Horizontal specific force (forward, left), ENU yaw rate and the levelled field (m_x, m_y).

        The body axes are FRD; a tilted IMU is rotated to the local level frame with the latest
        roll phi and pitch p: v_level = R_y(p) R_x(phi) v_body.
        """
        phi, p = self.roll, self.pitch
        if phi == 0.0 and p == 0.0:
            fx, fy = s.acc_x_mps2, s.acc_y_mps2
            yaw_rate_ned = s.gyro_z_radps
            mx, my = s.mag_x_gauss, s.mag_y_gauss
        else:
            cr, sr, cp, sp = math.cos(phi), math.sin(phi), math.cos(p), math.sin(p)
            fx = cp * s.acc_x_mps2 + sp * sr * s.acc_y_mps2 + sp * cr * s.acc_z_mps2
            fy = cr * s.acc_y_mps2 - sr * s.acc_z_mps2
            yaw_rate_ned = (sr * s.gyro_y_radps + cr * s.gyro_z_radps) / cp
            if s.mag_x_gauss is not None:
                mx = cp * s.mag_x_gauss + sp * sr * s.mag_y_gauss + sp * cr * s.mag_z_gauss
                my = cr * s.mag_y_gauss - sr * s.mag_z_gauss
            else:
                mx = my = None
        mag = (mx, my) if mx is not None and math.hypot(mx, my) > 1e-3 else None
        return fx, -fy, -yaw_rate_ned, mag

    # -- testing and fusing -----------------------------------------------------------------------
    def _measure(self, sensor, t_us, z, hx, H, R) -> list[Event]:
        r, S, PHT = self.ekf.innovation(z, hx, H, R)
        events, fused = self._test(sensor, t_us, r, S)
        if fused:
            self.ekf.fuse(r, S, H, R, PHT)
        return events

    def _test(self, sensor: str, t_us: int, r: np.ndarray, S: np.ndarray) -> tuple[list[Event], bool]:
        """Run the detector on one sensor's innovation; decide whether to fuse it."""
        stat, thr, hits = self.detector.test(sensor, t_us, r, S)
        if sensor == "gnss_vel":
            self._last_vel = (r, S)                 # the axis to name if a magnetometer alarm turns out to be it
            self._vel_t = t_us
        names = CHANNELS[sensor]
        events: list[Event] = []
        if sensor not in self.excluded:
            fused = True
            for i, offset in hits:
                named, ambiguous, channel = self._isolate(sensor) if sensor in ("mag", "gnss_vel") \
                    else (sensor, (), None)
                if named in self.excluded:
                    continue
                channel = names[i] if named == sensor else channel or CHANNELS[named][0]
                if named != sensor:                 # a witness named it: its own offset, not the alarm's
                    offset = self._gyro_bias() if named == "gyro" else self._lateral_bias()
                events.append(Alarm(t_us, self.gnss_index, named, channel, stat[i], thr[i], offset,
                                    self.detector.name, ambiguous))
                if self.cfg.exclude_on_alarm:
                    # one receiver gives GNSS position and velocity, and a spoofer controls both: both
                    # go; the one that still agrees is re-admitted after readmit_s
                    for out in self._receiver if named in RECEIVER else (named,):
                        if out not in self.excluded and out != named:
                            self._with_receiver.add(out)
                        self.excluded[out] = t_us
                        self._agreed.pop(out, None)
                    self._with_receiver.discard(named)
                    if named in RECEIVER:
                        # back to before the CUSUM's run began, its estimate of the onset; a velocity's
                        # run starts late (a spoof's offset grows slowly and the filter absorbs it as an
                        # accelerometer bias): back as far as the history goes
                        self._rewind_epochs = getattr(self.detector, "run_length", {}).get(sensor, 0) \
                            if sensor == "gnss_pos" else len(self._epochs)
                    if named == "accel" and named != sensor:
                        # the bias of the oldest epoch kept is taken for the sensor's own; what the filter
                        # absorbed since is the attack's, given back
                        self._accel_ref = float((self._epochs[0][1] if self._epochs else self.ekf.x)[BAY])
                        self.ekf.x[BAY] = self._accel_ref
            fused = sensor not in self.excluded
        else:
            fused = False
            agreed = self._agreed.pop(sensor, 0)    # samples in a row that agreed; any branch but the last resets it
            z = np.abs(r) / np.sqrt(np.diagonal(S))
            if hits or np.any(z > self.cfg.readmit_sigma):
                self.excluded[sensor] = t_us        # still inconsistent
            elif sensor == "gyro" and abs((self._turns() or (0.0,))[0]) >= TURN_Z[1]:
                self.excluded[sensor] = t_us        # its heading still turns away from the magnetometer's
            elif sensor == "accel" and self._accel_ref is not None and self._mag and \
                    t_us - self._mag[-1][0] < 1e6 and \
                    abs(self._lateral_bias() - self._accel_ref) >= self.cfg.filter.accel_sigma_mps2:
                self.excluded[sensor] = t_us        # it still reads sideways what the wheels do not do
            elif sensor == "gnss_pos" and "gnss_vel" in self.excluded and t_us - self._vel_t < 1e6:
                # a receiver whose velocity is still judged attacked: its position waits. (The filter's own
                # uncertainty grows while both are out, which would let a spoofed position "agree".)
                self.excluded[sensor] = t_us
            elif t_us - self.excluded[sensor] < self.cfg.readmit_s * 1e6 or agreed + 1 < READMIT_SAMPLES:
                self._agreed[sensor] = agreed + 1
            else:
                events += self._readmit(sensor, t_us)
                if sensor == "gnss_pos" and "gnss_vel" in self.excluded:
                    events += self._readmit("gnss_vel", t_us)   # fixes without a velocity: back with its receiver
                fused = True
        if self.record_tests:
            events.insert(0, Tested(Innovation(t_us, sensor, names, r, S, fused), self.gnss_index, stat, thr))
        return events, fused
