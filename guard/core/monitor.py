"""The core: one object with one pure, synchronous step. Sample in, events out, no I/O.

Live MAVLink, log replay, the CAN path and the tests all run this same object. `Monitor.step` is
the orchestration; each part owns its data and never calls back:
    aiding/     the measurements (z, h(x), H, R) of each sensor group      guard.core.aiding
    ekf         the filter's predict, innovation and fuse                    guard.core.ekf
    detector    the test of each innovation                                  guard.core.detectors
    health      exclusion and re-admission                                   guard.core.health
    isolation   the heading's witnesses: which sensor an alarm names        guard.core.isolation
    history     the rewind after a GNSS alarm, a late receiver's states      guard.core.history

Per IMU sample: level the IMU with the autopilot's roll and pitch (a flying drone is tilted), average
a fast IMU down to `imu_fusion_hz`, predict the filter to the sample's time, form the innovations
of heading, gyro and accelerometer, test them, fuse them. Per GNSS sample: the same with position
and velocity, then an Estimate. A GNSS alarm rewinds the filter to before the attack at the next
sample, once the alarm is out; the alarm epoch's Estimate waits for it and comes out with that
sample's events. A ground vehicle (`vehicle`, from the autopilot's HEARTBEAT by default) also has
v_y = 0 fused with every IMU update.
"""

from __future__ import annotations

import datetime
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from guard.core.aiding import Aid
from guard.core.aiding.gnss import FreezeWatch, GnssAiding
from guard.core.aiding.imu import Averager, ImuAiding, heading, level
from guard.core.detectors import DetectorConfig, make_detector
from guard.core.ekf import BAY, BW, N_STATES, TH, VX, VY, FilterConfig, NavEKF
from guard.core.geo import WMM_EPOCH, LocalFrame, declination_rad
from guard.core.health import Health
from guard.core.history import History, ImuFusion, state_minus
from guard.core.isolation import TURN_Z, HeadingWitness, Witnesses
from guard.model.events import Alarm, Estimate, Event, Innovation, Notice, Tested
from guard.model.samples import Attitude, GnssFix, ImuSample, VehicleType
from guard.model.sensors import CHANNELS, RECEIVER, Sensor

REWIND_S = 20.0        # s of filter history kept to undo what a GNSS attack fed the filter before its alarm


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
    `date`: when the data was recorded, for the magnetic declination: a replay passes its log's, the
    daemon today's (the core never reads the clock); None: the World Magnetic Model's epoch.
    """

    def __init__(self, cfg: MonitorConfig | None = None, record_tests: bool = True,
                 date: datetime.date | None = None):
        self.cfg = cfg or MonitorConfig()
        self.record_tests = record_tests
        self.date = date
        f = self.cfg.filter
        n_channels = sum(len(c) for s, c in CHANNELS.items() if s != Sensor.GNSS_VEL or f.use_gnss_velocity)
        self.detector = make_detector(self.cfg.detector, n_channels)
        self.gnss_aid = GnssAiding(f)
        self.imu_aid = ImuAiding(f)
        self.ground = self.cfg.vehicle == "ground"
        self._receiver = RECEIVER if f.use_gnss_velocity else (Sensor.GNSS_POS,)
        self.skipped: Counter[str] = Counter()
        self.gnss_index = -1
        self.roll = self.pitch = 0.0
        self._last_mag: tuple[float, float] | None = None     # levelled (m_x, m_y) of the latest IMU sample
        self._reset()

    def _reset(self) -> None:
        f = self.cfg.filter
        self.ekf: NavEKF | None = None
        self.frame: LocalFrame | None = None
        self.declination = 0.0
        self.t_us: int | None = None
        self.gnss_lost = False
        self.health = Health(self._receiver, self.cfg.readmit_s)
        self.witnesses = Witnesses(f, self.cfg.freeze_speed_mps)
        self.history = History(REWIND_S, f.gnss_delay_s, self.cfg.imu_fusion_hz or 1000.0)
        self.freeze = FreezeWatch(self.cfg.freeze_speed_mps)
        self.averager = Averager(self.cfg.imu_fusion_hz)
        self.detector.reset()
        self._last_fix_t: int | None = None         # time stamp of the previous fix
        self._vel_t = -math.inf                     # time of the last GNSS velocity tested
        self._rewind_epochs = 0                     # a rewind owed: done at the next step, after the alarm is out
        self._estimate_owed: tuple[int, int] | None = None   # (t_us, gnss_index) of the alarm's epoch

    @property
    def excluded(self) -> dict[Sensor, int]:
        return self.health.excluded

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
            events += self.health.cleared_all(sample.t_us, self.gnss_index)
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
            self.history.rewind(self.ekf, self._rewind_epochs, self.t_us)
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
        ekf, history = self.ekf, self.history
        # the state's own time, which a fix stamped before the last IMU sample is not: the rewind
        # re-runs the IMU fusions after it, and only those
        history.epoch(self.t_us, ekf.x, ekf.P)
        events += self._freeze(fix)
        delayed = history.delay_s > 0
        xd = history.delayed(fix.t_us, self.t_us, ekf.x) if delayed else ekf.x     # the state the fix shows
        before = ekf.x.copy() if delayed else None
        events += self._measure(Sensor.GNSS_POS, fix.t_us, self.gnss_aid.position(fix, self.frame, xd))
        if delayed:                 # the position's correction, carried to the state the velocity is tested on
            xd = xd + state_minus(ekf.x, before)
        if self.cfg.filter.use_gnss_velocity and fix.vel_n_mps is not None:
            self.witnesses.add_course(fix, xd, ekf.P[TH, TH], self.ground)
            events += self._measure(Sensor.GNSS_VEL, fix.t_us, self.gnss_aid.velocity(fix, xd))
        if delayed:                 # the correction applies to the stored states too: the next fix sees it
            history.shift(state_minus(ekf.x, before))
        if self._rewind_epochs:     # this epoch raised an alarm that rewinds: its estimate comes after that
            self._estimate_owed = (fix.t_us, self.gnss_index)
        else:
            events.append(self._estimate(fix.t_us, self.gnss_index))
        return events

    def _estimate(self, t_us: int, gnss_index: int) -> Estimate:
        x, f = self.ekf.x, self.frame
        return Estimate(t_us, gnss_index, float(x[0]), float(x[1]), float(x[TH]), x.copy(),
                        np.diagonal(self.ekf.P).copy(), (f.lat0, f.lon0, f.alt0))

    def _freeze(self, fix: GnssFix) -> list[Event]:
        """A frozen (replayed or stuck) GNSS: its position and velocity are excluded together."""
        speed = math.hypot(self.ekf.x[VX], self.ekf.x[VY])
        if not self.freeze.frozen(fix, speed) or Sensor.GNSS_POS in self.health.excluded:
            return []
        if self.cfg.exclude_on_alarm:
            self.health.exclude(Sensor.GNSS_POS, fix.t_us)
        return [Alarm(fix.t_us, self.gnss_index, Sensor.GNSS_POS, "frozen", speed, self.cfg.freeze_speed_mps, 0.0,
                      "freeze")]

    def _initialise(self, fix: GnssFix) -> list[Event]:
        self.frame = LocalFrame(fix.lat_deg, fix.lon_deg, fix.alt_m)
        dec = self.cfg.declination_deg
        self.declination = (declination_rad(fix.lat_deg, fix.lon_deg, fix.alt_m, self.date or WMM_EPOCH)
                            if dec is None else math.radians(dec))
        x0 = np.zeros(N_STATES)
        ve, vn = fix.vel_e_mps or 0.0, fix.vel_n_mps or 0.0
        if self._last_mag is not None:
            th = heading(*self._last_mag, self.declination)
        else:
            th = math.atan2(vn, ve) if math.hypot(ve, vn) > 1.0 else 0.0
        x0[TH] = th
        # body velocity from the ground velocity: v_body = R(theta)^T v_en
        x0[VX] = math.cos(th) * ve + math.sin(th) * vn
        x0[VY] = -math.sin(th) * ve + math.cos(th) * vn
        self.ekf = NavEKF(self.cfg.filter, x0)
        self.t_us = fix.t_us
        return [Notice(fix.t_us, "info", f"filter initialised at {fix.lat_deg:.6f}, {fix.lon_deg:.6f}")]

    # -- IMU ------------------------------------------------------------------------------------
    def _imu(self, s: ImuSample) -> list[Event]:
        ax, ay, rate, mag = level(s, self.roll, self.pitch)
        self._last_mag = mag
        if self.ekf is None:
            self.skipped["imu_before_first_fix"] += 1
            return []
        due = self.averager.add(s.t_us, ax, ay, rate, mag)
        if due is None:
            return []
        ax, ay, rate, mag = due
        self._advance(s.t_us)
        theta = None if mag is None else heading(*mag, self.declination)
        if theta is None:
            self.skipped["imu_no_magnetometer"] += 1
        aid, blocks, angle = self.imu_aid.measurement(self.ekf.x, theta, rate, ax, ay, self.ground)
        z, _, H, R = aid
        r, S, PHT = self.ekf.innovation(z, aid.hx, H, R, angle_rows=angle)
        if theta is not None:
            self.witnesses.add_heading(HeadingWitness(s.t_us, theta, rate, ay, self.ekf.x[VX]))
        # one stacked update, tested sensor by sensor
        events: list[Event] = []
        keep: list[int] = []
        for sensor, i, j in blocks:
            ev, fused = self._test(sensor, s.t_us, r[i:j], S[i:j, i:j])
            events += ev
            if fused:
                keep.extend(range(i, j))
        if self.ground:
            keep.append(len(r) - 1)                # a constraint, not a sensor: never tested, always fused
        fusion = None
        if len(keep) == len(r):
            self.ekf.fuse(r, S, H, R, PHT)
            fusion = ImuFusion(s.t_us, z, H, R, angle)
        elif keep:
            ix = np.ix_(keep, keep)
            self.ekf.fuse(r[keep], S[ix], H[keep], R[ix], PHT[:, keep])
            fusion = ImuFusion(s.t_us, z[keep], H[keep], R[ix], angle if keep[0] == 0 else ())
        self.history.imu_fused(s.t_us, fusion, self.ekf.x)
        return events

    # -- testing and fusing -----------------------------------------------------------------------
    def _measure(self, sensor: Sensor, t_us: int, aid: Aid) -> list[Event]:
        r, S, PHT = self.ekf.innovation(aid.z, aid.hx, aid.H, aid.R)
        events, fused = self._test(sensor, t_us, r, S)
        if fused:
            self.ekf.fuse(r, S, aid.H, aid.R, PHT)
        return events

    def _test(self, sensor: Sensor, t_us: int, r: np.ndarray, S: np.ndarray) -> tuple[list[Event], bool]:
        """Run the detector on one sensor's innovation; decide whether to fuse it."""
        stat, thr, hits = self.detector.test(sensor, t_us, r, S)
        if sensor == Sensor.GNSS_VEL:
            self.witnesses.last_vel = (r, S)    # the axis to name if a magnetometer alarm turns out to be it
            self._vel_t = t_us
        if sensor not in self.health.excluded:
            events = self._alarms(sensor, t_us, hits, stat, thr)
            fused = sensor not in self.health.excluded
        else:
            events, fused = self._readmission(sensor, t_us, r, S, hits)
        if self.record_tests:
            events.insert(0, Tested(Innovation(t_us, sensor, CHANNELS[sensor], r, S, fused), self.gnss_index,
                                    stat, thr))
        return events, fused

    def _alarms(self, sensor: Sensor, t_us: int, hits, stat, thr) -> list[Event]:
        """The alarms of a sensor in use: named (isolation), raised, and what it excludes."""
        events: list[Event] = []
        health, bw = self.health, self.ekf.x[BW]
        for i, offset in hits:
            named, ambiguous, channel = self.witnesses.isolate(sensor, self.t_us, bw) \
                if sensor in (Sensor.MAG, Sensor.GNSS_VEL) else (sensor, (), None)
            if named in health.excluded:
                continue
            channel = CHANNELS[sensor][i] if named == sensor else channel or CHANNELS[named][0]
            if named != sensor:                 # a witness named it: its own offset, not the alarm's
                offset = self.witnesses.gyro_bias() if named == Sensor.GYRO else self.witnesses.lateral_bias(bw)
            events.append(Alarm(t_us, self.gnss_index, named, channel, stat[i], thr[i], offset,
                                self.detector.name, ambiguous))
            if not self.cfg.exclude_on_alarm:
                continue
            health.exclude(named, t_us)
            if named in RECEIVER:
                # back to before the CUSUM's run began, its estimate of the onset; a velocity's run starts
                # late (a spoof's offset grows slowly and the filter absorbs it as an accelerometer
                # bias): back as far as the history goes
                self._rewind_epochs = self.detector.run_length.get(sensor, 0) \
                    if sensor == Sensor.GNSS_POS else len(self.history)
            if named == Sensor.ACCEL and named != sensor:
                # the bias of the oldest epoch kept is taken for the sensor's own; what the filter
                # absorbed since is the attack's, given back
                oldest = self.history.oldest_x()
                health.accel_ref = float((oldest if oldest is not None else self.ekf.x)[BAY])
                self.ekf.x[BAY] = health.accel_ref
        return events

    def _readmission(self, sensor: Sensor, t_us: int, r, S, hits) -> tuple[list[Event], bool]:
        """An excluded sensor's test: re-admitted once it has agreed long enough and no witness holds it."""
        z = np.abs(r) / np.sqrt(np.diagonal(S))
        bad = bool(hits) or bool(np.any(z > self.cfg.readmit_sigma)) or self._held(sensor, t_us)
        if not self.health.settle(sensor, t_us, bad):
            return [], False
        events = self._readmit(sensor, t_us)
        if sensor == Sensor.GNSS_POS and Sensor.GNSS_VEL in self.health.excluded:
            events += self._readmit(Sensor.GNSS_VEL, t_us)   # fixes without a velocity: back with its receiver
        return events, True

    def _held(self, sensor: Sensor, t_us: int) -> bool:
        """A witness still holds an excluded sensor whose own innovation agrees."""
        bw, witnesses = self.ekf.x[BW], self.witnesses
        if sensor == Sensor.GYRO:               # its heading still turns away from the magnetometer's
            return abs((witnesses.turns(self.t_us, bw) or (0.0,))[0]) >= TURN_Z[1]
        if sensor == Sensor.ACCEL:              # it still reads sideways what the wheels do not do
            ref = self.health.accel_ref
            return ref is not None and witnesses.fresh(t_us) and \
                abs(witnesses.lateral_bias(bw) - ref) >= self.cfg.filter.accel_sigma_mps2
        if sensor == Sensor.GNSS_POS:
            # a receiver whose velocity is still judged attacked: its position waits. (The filter's own
            # uncertainty grows while both are out, which would let a spoofed position "agree".)
            return Sensor.GNSS_VEL in self.health.excluded and t_us - self._vel_t < 1e6
        return False

    def _readmit(self, sensor: Sensor, t_us: int) -> list[Event]:
        self.detector.forget(sensor)                # a fresh test: what it summed while excluded is spent
        return self.health.readmit(sensor, t_us, self.gnss_index)
