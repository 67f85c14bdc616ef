"""The core: one object with one pure, synchronous step. Sample in, events out, no I/O.

Live MAVLink, log replay, the CAN path and the tests all run this same object. `Monitor.step` is
the orchestration; each part owns its data and never calls back:
    aiding/     the measurements (z, h(x), H, R) of each sensor group      guard.core.aiding
    ekf         the filter's predict, innovation and fuse                    guard.core.ekf
    detector    the test of each innovation                                  guard.core.detectors
    health      exclusion and re-admission                                   guard.core.health
    isolation   the heading's witnesses: which sensor an alarm names        guard.core.isolation
    history     the rewind after a GNSS alarm, a late receiver's states      guard.core.history
    drift       how far the IMU alone strays on this vehicle, for a coast   guard.core.drift

Per IMU sample: level the IMU with the autopilot's roll and pitch (a flying drone is tilted), set it
aside within 0.5 s of a blow over 3 g (aiding/impact: a landing's point sample is no acceleration to
integrate), average a fast IMU down to `imu_fusion_hz`, predict the filter to the sample's time, form the innovations
of heading, gyro and accelerometer, test them, fuse them; on GNSS alone (no compass), a fast IMU's
samples only say how much the acceleration changed (aiding/manoeuvre), which widens the model at
the next fix. Per GNSS sample: the same with position and velocity, then an Estimate. A GNSS alarm rewinds the filter to before the attack at the next
sample, once the alarm is out; the alarm epoch's Estimate waits for it and comes out with that
sample's events. A ground vehicle (`vehicle`, from the autopilot's HEARTBEAT by default) also has
v_y = 0 fused with every IMU update, its innovation tested as the accelerometer's "lateral" channel
(`test_lateral`).
"""

from __future__ import annotations

import dataclasses
import datetime
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from guard.core.aiding import Aid
from guard.core.aiding.compass import NO_COMPASS_S, CompassWatch
from guard.core.aiding.gnss import (HELD_COURSE_MAX_MPS, START_H_ACC_M, START_HDOP, FreezeWatch, GnssAiding,
                                    across_track, gnss_velocity_model)
from guard.core.aiding.impact import BUDGET_S, HOLD_S, IMPACT_G, MEAN_S, WINDOW_S, Impact
from guard.core.aiding.imu import NOISE_CAP, Averager, ImuAiding, RateWatch, fuse_rows, heading, level, row_sensors
from guard.core.aiding.manoeuvre import AccelChange
from guard.core.aiding.noisecap import NoiseCap
from guard.core.aiding.motors import MotorWatch, offset_q
from guard.core.aiding.tilt import Tilt
from guard.core.aiding.rest import RestCheck
from guard.core.aiding.vertical import VerticalCheck
from guard.core.anchor import Learnt, diverged, initial_state
from guard.core.detectors import DetectorConfig, make_detector
from guard.core.drift import Drift
from guard.core.ekf import BM, TH, VX, VY, FilterConfig, NavEKF
from guard.core.geo import WMM_EPOCH, LocalFrame, declination_rad
from guard.core.fit import ModelFit
from guard.core.health import Health
from guard.core.history import REWIND_S, History, state_minus
from guard.core.isolation import HeadingWitness, Witnesses
from guard.core.judge import CALM_RATIO, Judge
from guard.core.longrun import LongRun
from guard.core.timebase import SOLE_SPAN_US, Timebase
from guard.model.events import Estimate, Event, Notice
from guard.model.samples import Attitude, GnssFix, ImuSample, VehicleType
from guard.model.sensors import CHANNELS, RECEIVER, Sensor

MAX_FIX_INTERVAL_S = 2.0   # s: fixes further apart say nothing of the acceleration between them (a gap)
KIND_WAIT_S = 10.0     # s of monitoring without the vehicle's type (a HEARTBEAT comes every second): not sent
SOLE_SAID = {"gnss": "GNSS fixes", "imu": "IMU samples"}
NO_IMU_S = 10.0      # s of fixes without any IMU sample: the GNSS is tested alone (_imu_absent)
IMU_SILENT_S = 3.0    # s without an IMU sample while it is integrated: its states carried unmeasured (said)
CAP_FIXES = 5          # fixes in a row whose receiver calls itself worse than guard takes: then said


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
    max_coast_m: float = 20.0               # m (1 sigma): an excluded GNSS the other sensors cannot hold the
                                            # estimate against for longer is re-anchored on, its alarm standing
    max_coast_heading_deg: float = 20.0     # deg (1 sigma): an excluded compass the other sensors cannot hold
                                            # the heading against for longer is re-anchored on, its alarm standing
    min_imu_hz: float = 8.0                 # Hz: a slower IMU stream (telemetry) is not integrated
    max_wander_factor: float = 1.0          # the most a test is widened for its innovations' wander
                                            # (guard.core.longrun); 1, the default: as the model says
    test_lateral: bool = True               # on wheels, the sideways constraint's innovation is tested as the
                                            # accelerometer's channel "lateral" (not only fused)


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
        if self.cfg.vehicle == "air" or not self.cfg.test_lateral:
            n_channels -= 1                         # no wheels, or not tested: no "lateral" channel
        self.detector = make_detector(self.cfg.detector, n_channels)
        self.gnss_aid = GnssAiding(f)
        self.imu_aid = ImuAiding(f)
        self.ground = self.cfg.vehicle == "ground"
        self._kind_told = self.cfg.vehicle != "auto"   # the config or the source said ground or air
        self._kind_wait_from: int | None = None     # the first fix monitored while neither has
        self._receiver = RECEIVER if f.use_gnss_velocity else (Sensor.GNSS_POS,)
        self.skipped: Counter[str] = Counter()
        # samples used, but not as they came (their variance widened): counted apart from the skipped
        self.adjusted: Counter[str] = Counter()
        self.timebase = Timebase(self.cfg.max_gap_s, self.skipped)
        self.fit = ModelFit()
        # each test's scale for its innovations' wander, the vehicle's (kept through a restart); off at 1
        self.longrun = LongRun(self.cfg.max_wander_factor) if self.cfg.max_wander_factor > 1.0 else None
        self.gnss_index = -1
        self.tilt = Tilt()                          # the autopilot's roll and pitch, at each IMU sample's time
        self.manoeuvre = AccelChange()              # on GNSS alone, how much the IMU says the acceleration changed
        self.inertial: bool | None = None           # None until the IMU's rate is known; False: too slow
        self.imu_rate = RateWatch(self.cfg.min_imu_hz)
        self.compass = CompassWatch()               # whether an air vehicle has a compass at all
        self.motors = MotorWatch()                  # the motors' start and stop, heard in the IMU
        self.vertical = VerticalCheck()             # the accelerometers' vertical reading against the altitude
        self.rest = RestCheck()                     # ... and their reading of gravity at rest
        self.noise_cap = NoiseCap(NOISE_CAP)        # an IMU noisier than the tests take: said once per sensor
        self._last_mag: tuple[float, float] | None = None     # levelled (m_x, m_y) of the latest IMU sample
        self._learnt: Learnt | None = None          # what a restarted filter keeps of the vehicle (_reinitialise)
        self._fix: GnssFix | None = None            # the latest fix, and where it is in the local frame
        self._fix_en: tuple[float, float] | None = None
        self.drift = Drift()                        # the IMU's open-loop drift, measured in flight (the vehicle's)
        self._held_said = False                     # the receiver holds its course at low speed: said once
        self._usual_said = False                    # a receiver poorer than the fixed bound all along: likewise
        self._beyond_said = False                   # ... or than guard tune believes of this vehicle: likewise
        self._imu_silent = False                    # an integrated IMU's stream fell silent (said), not yet back
        self._imu_silent_since: int | None = None   # ... its last sample's time, where on the same clock
        self._started_us: int | None = None         # the filter's first fix: the IMU's silence counts from it at most
        self._imu_unmeasured = False                # the filter carries the IMU's states unmeasured (a gap)
        self._imu_silence_said = False              # an IMU silence is said once a filter
        self._reset()

    def _reset(self) -> None:
        f = self.cfg.filter
        self.ekf: NavEKF | None = None
        self._held = False                          # the latest fix's course was held by its receiver
        self.gnss_aid.forget_course()               # and a new filter's first fix starts the course over
        self.frame: LocalFrame | None = None
        self.declination = 0.0
        self.t_us: int | None = None
        self.gnss_lost = False
        self.health = Health(self._receiver, self.cfg.readmit_s)
        self.health.lateral = self.ground and self.cfg.test_lateral
        self.witnesses = Witnesses(f, self.cfg.freeze_speed_mps)
        self.history = History(REWIND_S, f.gnss_delay_s, self.cfg.imu_fusion_hz or 1000.0)
        self.judge = Judge(self.cfg, self.detector, self.health, self.witnesses, self.history, self.longrun)
        self.judge.air = not self.ground
        self.freeze = FreezeWatch(self.cfg.freeze_speed_mps)
        self.averager = Averager(self.cfg.imu_fusion_hz)
        self.impact = Impact()
        self.drift.restart()
        self.manoeuvre.reset()
        self._coast_from: int | None = None         # the time of the last GNSS position the estimate holds
        self.detector.reset()
        self._heading_unset = False                 # the filter started before the magnetometer spoke
        self._coarse_said = False                   # a fix too coarse to start on: said once per start
        self._cap_said = False                      # a receiver worse than guard takes its word for: likewise,
        self._cap_run = 0                           # once it has said so CAP_FIXES fixes in a row
        self._estimate_owed: tuple[int, int] | None = None   # (t_us, gnss_index) of the alarm's epoch
        self._v_fixed: tuple[int, np.ndarray] | None = None   # (t_us, velocity east-north) after the last fix

    @property
    def excluded(self) -> dict[Sensor, int]:
        return self.health.excluded

    @property
    def alarmed(self) -> set[Sensor]:
        """The sensors whose alarm stands (excluded, or latched after a re-anchoring or a restart)."""
        return self.health.alarmed()

    # -- the step -----------------------------------------------------------------------------
    def step(self, sample) -> list[Event]:
        if isinstance(sample, Attitude):
            self.tilt.set(sample)
            return []
        if isinstance(sample, VehicleType):
            return self._vehicle(sample)
        events = self.finish()                      # an alarm's rewind, then its epoch's Estimate, if owed
        gnss = isinstance(sample, GnssFix)
        if not (gnss and not sample.fix_ok):        # a no-fix message's time means nothing
            kind = "gnss" if gnss else "imu"
            alone = self.inertial is False and self.t_us is not None        # on GNSS alone: the IMU keeps the clock
            if gnss and alone and sample.t_us - self.t_us > self.cfg.max_gap_s * 1e6 and \
                    self.timebase.on_imu_clock(sample.t_us):
                # a fix after a silence nothing carried the estimate through: a new filter starts on it
                events += self._reinitialise(sample.t_us, f"no GNSS fix for {(sample.t_us - self.t_us) / 1e6:.1f} s "
                                             "on GNSS alone", keep_learnt=True)
                verdict = self.timebase.check(kind, sample.t_us, None)
            else:
                verdict = self.timebase.check(kind, sample.t_us, self.t_us, own_clock=alone and not gnss)
            if verdict == "drop":                   # not a sample of the stream: not counted in k either
                return events
            if verdict == "rebase":
                base = self.t_us if self.t_us is not None else self.timebase.last[kind]   # no filter yet
                sole = self.timebase.sole
                jump = (sample.t_us - base) / 1e6
                ahead = " (every stream silent that long, or their clock set on)" if jump > 0 else ""
                why = f"time jumped {jump:+.1f} s{ahead}" if sole is None else (
                    f"time jumped {(sole[1] - base) / 1e6:+.1f} s by the {SOLE_SAID[sole[0]]} alone, the other "
                    f"stream silent over {SOLE_SPAN_US / 1e6:g} s of them")
                events += self._reinitialise(sample.t_us, why, keep_learnt=True)
                self.timebase.check(kind, sample.t_us, None)
        if gnss:
            self.gnss_index += 1
            events += self._gnss(sample)
        elif isinstance(sample, ImuSample):
            events += self._imu(sample)
        return events

    def finish(self) -> list[Event]:
        """At the end of a stream: what the last step still owed (an alarm's rewind and its epoch's
        Estimate, which wait for the next sample)."""
        events: list[Event] = []
        if self.judge.rewind_epochs:
            back_to = self.history.rewind(self.ekf, self.judge.rewind_epochs, self.t_us,
                                          frozenset(self.health.excluded))
            if back_to is not None:
                self._coast_from = back_to
            self.drift.restart()
            self._v_fixed = None
            self.judge.rewind_epochs = 0
            # what the rewind left may already be more than the other sensors can hold (GNSS alone, where
            # nothing else holds the position, or a long rewind in the air): then the alarm epoch's own
            # fix is the anchor, as the next one would be, and the estimate shown never coasts away
            events += self._reanchor(self._fix)
        if self._estimate_owed:
            events.append(self._estimate(*self._estimate_owed))
            self._estimate_owed = None
        return events

    def _reinitialise(self, t_us: int, why: str, keep_learnt: bool = False) -> list[Event]:
        """A new filter, from the next fix. Its alarms are cleared but a GNSS one's, which stands.

        `keep_learnt`: the vehicle is the one it was (a reboot, a link back after an outage), so the
        new filter starts from what the old one learnt of it, the compass's offset b_psi, the
        wheels' slip k_s and the sensors' place ahead of the axle d with their variances, not from the
        config's values: the heading is right from the first fix and nothing is learnt twice. An
        autopilot calibrates its gyro and accelerometers at boot, so their biases start anew. A
        diverged filter keeps nothing: what it learnt may be what went wrong."""
        events: list[Event] = [Notice(t_us, "warning", f"{why}: filter re-initialised")]
        self.vertical.gap()
        self._learnt = Learnt.of(self.ekf) if keep_learnt and self.ekf is not None else None
        if self._learnt is not None:
            events.append(Notice(t_us, "info", f"kept what it learnt of the vehicle: {self._learnt}"))
        cleared, kept = self.health.carried(t_us, self.gnss_index)
        events += cleared
        if kept:
            events.append(Notice(t_us, "warning", f"the {' and '.join(sorted(kept))} alarm stands: a new "
                                 "filter starts on the GNSS"))
        last_alarm = self.judge.last_alarm
        self._reset()
        self.timebase.reset()
        self._kind_wait_from = None                 # 10 s of monitoring by the new clock
        self._imu_silent, self._imu_silent_since = False, None     # a new filter says a silence anew
        self._imu_unmeasured = False                # a new filter's model is the IMU's
        self._imu_silence_said = False
        self.health.latched |= kept
        self.judge.last_alarm = {s: v for s, v in last_alarm.items() if s in kept}   # a standing alarm goes on
        return events

    def _vehicle(self, v: VehicleType) -> list[Event]:
        self._kind_told = True
        if self.cfg.vehicle != "auto" or v.ground == self.ground:
            return []
        self.ground = v.ground
        self.health.lateral = v.ground and self.cfg.test_lateral
        self.judge.air = not v.ground
        if self.ekf is not None and self.inertial is not False:
            self.ekf.tilting(not v.ground)
        what = ("a ground vehicle: its sideways velocity is held at zero" if v.ground
                else "a vehicle that may move sideways: sideways velocity left free")
        return [Notice(self.t_us or 0, "info", f"the autopilot reports {what}")]

    def _kind_unsaid(self, t_us: int) -> list[Event]:
        """Said once: `auto` and a source that has not said what the vehicle is (DroneCAN, a log
        without the autopilot's HEARTBEAT) within KIND_WAIT_S of monitoring. The air model stands:
        it holds no sideways velocity at zero, so a car is not falsely alarmed but its heading and a
        sideways accelerometer attack are tested less sharply than "ground" tests them."""
        if self._kind_told:
            return []
        if self._kind_wait_from is None or t_us < self._kind_wait_from:    # a clock set back: wait anew
            self._kind_wait_from = t_us
        if t_us - self._kind_wait_from < KIND_WAIT_S * 1e6:
            return []
        self._kind_told = True
        return [Notice(t_us, "warning", f'monitor.vehicle is "auto" and in {KIND_WAIT_S:g} s the source has not '
                       "said what the vehicle is (an autopilot's HEARTBEAT says it, DroneCAN does not): modelled "
                       'as one that may move sideways; set monitor.vehicle = "ground" for a wheeled vehicle, '
                       '"air" to say so')]

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
                lost = "GNSS fix lost: coasting on the IMU" if self.inertial else \
                    "GNSS fix lost: nothing holds the estimate (on GNSS alone, the IMU not integrated)"
                events.append(Notice(fix.t_us, "warning", lost if self.ekf
                                     else "GNSS without a fix: monitoring starts at the first fix"))
            return events
        if self.gnss_lost:
            self.gnss_lost = False
            events.append(Notice(fix.t_us, "info", "GNSS fix back" if self.ekf else "GNSS fix: monitoring starts"))
        events += self.vertical.fix(fix.t_us, fix.alt_m)
        self.rest.fix(fix.t_us, None if fix.vel_n_mps is None else math.hypot(fix.vel_n_mps, fix.vel_e_mps))
        if self.ekf is None:
            coarse = self.gnss_aid.too_coarse_to_start(fix)
            if coarse:                              # a receiver still finding itself is no reference
                self.skipped["gnss_coarse_before_start"] += 1
                if not self._coarse_said:
                    self._coarse_said = True
                    events.append(Notice(fix.t_us, "info", f"GNSS fix good to {coarse} only: monitoring starts "
                                         f"once the receiver reports {START_H_ACC_M:g} m or HDOP {START_HDOP:g}"))
                return events
        # what the receiver usually says of itself (guard.core.aiding.receiver), heard while no test stirs;
        # a new filter's first fix is tested by nothing, and heard unless an alarm stands through the
        # restart (a reboot or an outage mid-attack: that fix is the attacker's as much as the last)
        self.gnss_aid.level.hear(fix, (self.judge.calm and not self.health.excluded) if self.ekf is not None
                                 else not self.health.latched)
        usual = None if self._usual_said else self.gnss_aid.poor_as_usual()
        if usual:
            self._usual_said = True
            events.append(Notice(fix.t_us, "warning", usual))
        beyond = None if self._beyond_said else self.gnss_aid.beyond_usual()
        if beyond:
            self._beyond_said = True
            events.append(Notice(fix.t_us, "warning", beyond))
        if self.ekf is None:
            return events + self._initialise(fix)
        events += self._kind_unsaid(fix.t_us)
        events += self._imu_quiet(fix.t_us) + self._imu_absent(fix.t_us)
        poor = None if self._cap_said else self.gnss_aid.beyond_cap(fix)
        self._cap_run = self._cap_run + 1 if poor else 0
        if poor and self._cap_run >= CAP_FIXES:     # a receiver that says so for a while, not one odd fix
            self._cap_said = True
            events.append(Notice(fix.t_us, "warning", poor))
        self.ekf.wander(self.gnss_aid.q_pos(fix))
        T = (fix.t_us - self.t_us) / 1e6
        self._advance(fix.t_us)
        if self.inertial is False:
            sx, sy = self.imu_aid.noise.measured(1)[:2]
            da = self.manoeuvre.change(fix.t_us, sx * sx + sy * sy)
            if da > 0.0 and T > 0.0:
                self.ekf.manoeuvred(da, T)
                self.history.manoeuvre(fix.t_us, da, T)
                if da > self.cfg.filter.q_accel_no_imu_mps2 * math.sqrt(T):    # past the model's own walk
                    self.adjusted["gnss_manoeuvre_widened"] += 1
        why = diverged(self.ekf)
        if why:
            return events + self._reinitialise(fix.t_us, f"the filter diverged ({why})") + self._initialise(fix)
        ekf, history = self.ekf, self.history
        self._fix, self._fix_en = fix, self.frame.to_en(fix.lat_deg, fix.lon_deg)
        events += self._held_course(fix)
        # the acceleration a late fix lags by, where its latency's uncertainty is set (GnssAiding.latency_spread);
        # on GNSS alone no IMU for a fix to lag
        lagging = bool(self.inertial) and self.gnss_aid.latency_sigma(bool(self.ground)) > 0.0
        accel = self._accel_since_fix() if lagging else None
        # the state's own time, which a fix stamped before the last IMU sample is not: the rewind
        # re-runs the IMU fusions after it, and only those
        history.epoch(self.t_us, ekf.x, ekf.P)
        events += self._freeze(fix)
        events += self._reanchor(fix)
        delayed = history.delay_s > 0
        xd = history.delayed(fix.t_us, self.t_us, ekf.x) if delayed else ekf.x     # the state the fix shows
        before = ekf.x.copy() if delayed else None
        events += self._measure(Sensor.GNSS_POS, fix.t_us, self.gnss_aid.position(fix, self._fix_en, xd))
        if delayed:                 # the position's correction, carried to the state the velocity is tested on
            xd = xd + state_minus(ekf.x, before)
        if self.cfg.filter.use_gnss_velocity and fix.vel_n_mps is not None:
            aid = self.gnss_aid.velocity(fix, xd, accel, bool(self.ground), self._held, ekf.P)
            self.witnesses.add_course(fix, xd, ekf.P[TH, TH], self.ground, across_track(aid.R, fix), self._held)
            events += self._measure(Sensor.GNSS_VEL, fix.t_us, aid, modelled=not self._held)
        self._probe(fix)
        if delayed:                 # the correction applies to the stored states too: the next fix sees it
            history.shift(state_minus(ekf.x, before))
        events += self.fit.check(fix.t_us)
        self._v_fixed = (self.t_us, gnss_velocity_model(ekf.x)[0]) if lagging else None
        if self.judge.rewind_epochs:    # this epoch raised an alarm that rewinds: its estimate comes after that
            self._estimate_owed = (fix.t_us, self.gnss_index)
        else:
            events.append(self._estimate(fix.t_us, self.gnss_index))
        return events

    def _imu_quiet(self, t_us: int) -> list[Event]:
        """An integrated IMU silent over IMU_SILENT_S at this fix (its stream stopped, its rate set to
        0 on the link): from here the filter holds the heading and carries the acceleration as nothing
        measures them (NavEKF.unmeasured), and the IMU's return gives the heading back to the next
        compass reading, as at a start (`_imu`). Predicted as if the IMU were there, the fixes turned
        the heading through correlations nothing measured (130 degrees in 12 s), and the first fusion
        after a silence of 4 s or more raised an alarm (the compass's, the accelerometer's or the GNSS
        velocity's) on half the tests' clean drives. Nothing else changes: the tests, the alarms that
        stand and what the filter learnt go on through it (a new filter at its end, tried first, gave a
        standing alarm's protection away to whoever could drop the IMU's frames for a few seconds; a
        compass whose alarm stands gives no heading back). Said once a filter, and its end. The first
        IMU_SILENT_S are still predicted as if the IMU were there (the heading may turn by then), and
        while the heading is held its variance reads 0."""
        last = self.timebase.last.get("imu")
        ref = last if last is not None else self._started_us
        if not self.inertial or ref is None or t_us - ref <= IMU_SILENT_S * 1e6:
            return []
        if not self._imu_unmeasured:
            self._imu_unmeasured = True
            self.ekf.unmeasured(True, not self.ground)
        if self._imu_silent or self._imu_silence_said:
            return []                               # said once a filter: a slow IMU's every interval is not news
        self._imu_silent = self._imu_silence_said = True
        self._imu_silent_since = last
        since = f"for {(t_us - last) / 1e6:.1f} s" if last is not None else "since the filter started"
        return [Notice(t_us, "warning", f"no IMU sample {since}: the accelerometer, gyro and compass untested until "
                       "it is back, the GNSS holding the estimate")]

    def _imu_absent(self, t_us: int) -> list[Event]:
        """A stream with no IMU at all (a ground station's tlog of an autopilot that sends only its
        ATTITUDE): after NO_IMU_S of fixes without one IMU sample, the GNSS is tested alone, as for an
        IMU too slow to integrate, the heading held. Run as if an IMU would come, the heading and yaw
        rate, measured by nothing, wandered as random walks and turned the body velocity through the
        transport term, and the filter diverged within a minute or two (five times in 46 minutes of a
        real hexacopter's tlog). An IMU that speaks later is integrated from then on, by a new filter."""
        if self.inertial is not None or self._started_us is None or t_us - self._started_us < NO_IMU_S * 1e6 \
                or self.timebase.last.get("imu") is not None:
            return []
        self.inertial = False
        self.ekf.hold_heading()
        self._heading_unset = False
        what = (f"IMU samples heard in {NO_IMU_S:g} s of GNSS, none on its clock (counted as time_off_base: "
                "see the source's time stamps, time_source on CAN)" if "imu" in self.timebase.heard
                else f"no IMU sample in {NO_IMU_S:g} s of GNSS")
        return [Notice(t_us, "warning", f"{what}: not integrated; GNSS position and velocity are tested against "
                       "each other alone (jumps, freezes, drifts)")]

    def _accel_since_fix(self) -> np.ndarray | None:
        """The mean horizontal acceleration (east, north) since the last fix: the filter's velocity change
        as the IMU carried it, no fix fused between, before this one is (what a receiver's latency shows,
        GnssAiding.latency_spread). None after a start, a rewind or a gap of over MAX_FIX_INTERVAL_S."""
        if self._v_fixed is None:
            return None
        t0, v0 = self._v_fixed
        dt = (self.t_us - t0) / 1e6
        if not 0.0 < dt <= MAX_FIX_INTERVAL_S:
            return None
        return (gnss_velocity_model(self.ekf.x)[0] - v0) / dt

    def _estimate(self, t_us: int, gnss_index: int) -> Estimate:
        x, f = self.ekf.x, self.frame
        return Estimate(t_us, gnss_index, float(x[0]), float(x[1]), float(x[TH]), x.copy(),
                        np.diagonal(self.ekf.P).copy(), (f.lat0, f.lon0, f.alt0), self._fix_en,
                        Sensor.GNSS_POS not in self.health.excluded)

    def _held_course(self, fix: GnssFix) -> list[Event]:
        """Whether the fix's course was held by its receiver (GnssAiding.held_course): its velocity, tested
        or anchored on, then has its direction taken as unknown. Counted, and said once."""
        self._held = (self.cfg.filter.use_gnss_velocity and fix.vel_n_mps is not None
                      and self.gnss_aid.held_course(fix))
        if not self._held:
            return []
        self.adjusted["gnss_course_held"] += 1
        if self._held_said:
            return []
        self._held_said = True
        return [Notice(fix.t_us, "info", "the receiver holds its course over ground at low speed (a course "
                       f"repeated to the last digit under {HELD_COURSE_MAX_MPS:g} m/s): such a fix's velocity is "
                       "taken with its direction unknown (counted as gnss_course_held)")]

    def _reanchor(self, fix: GnssFix) -> list[Event]:
        """An exclusion has a bounded life (Judge.reanchor), as long as the filter's uncertainty and the
        drift measured on this vehicle (guard.core.drift) say the estimate can be held."""
        if Sensor.GNSS_POS not in self.health.excluded:
            return []
        coast_s = (fix.t_us - self._coast_from) / 1e6 if self._coast_from is not None else 0.0
        # the drift is an air vehicle's IMU's alone: a coast the GNSS velocity holds, a wheeled vehicle's
        # (its sideways constraint holds it) and one on GNSS alone are the filter's to judge
        alone = (Sensor.GNSS_VEL in self.health.excluded or fix.vel_n_mps is None or
                 not self.cfg.filter.use_gnss_velocity) and not self.ground and bool(self.inertial)
        widen = (lambda sigma: self.drift.widened(sigma, coast_s)) if alone else None
        events = self.judge.reanchor(self.ekf, fix, self._fix_en, self.gnss_aid, self.cfg.max_coast_m,
                                     self.gnss_index, widen, self._held, gnss_only=not self.inertial)
        if events:
            self._coast_from = fix.t_us
        return events

    def _probe(self, fix: GnssFix) -> None:
        """The drift's probes (guard.core.drift), on an inertial air vehicle: measured at a fix fused, one
        started at a fix fused with every test calm; they end when the GNSS is set aside."""
        if Sensor.GNSS_POS in self.health.excluded:
            self.drift.restart()
            return
        self._coast_from = fix.t_us
        if self.ground or not self.inertial:
            return
        calm = self.judge.calm
        # a late receiver's fix shows the vehicle gnss_delay_s before its time stamp
        self.drift.fix(fix.t_us - int(self.history.delay_s * 1e6), self._fix_en, calm)
        if calm:
            self.drift.start(fix.t_us, self.ekf.x)

    def _freeze(self, fix: GnssFix) -> list[Event]:
        """A frozen (replayed or stuck) GNSS: its position and velocity are excluded together."""
        alarm = self.freeze.check(fix, math.hypot(self.ekf.x[VX], self.ekf.x[VY]), self.gnss_index)
        if alarm is None or Sensor.GNSS_POS in self.health.excluded:
            return []
        alarm = dataclasses.replace(alarm, standing=self.judge.record_alarm(Sensor.GNSS_POS, fix.t_us))
        if self.cfg.exclude_on_alarm:
            self.health.exclude(Sensor.GNSS_POS, fix.t_us)
        return [alarm]

    def _initialise(self, fix: GnssFix) -> list[Event]:
        self.frame = LocalFrame(fix.lat_deg, fix.lon_deg, fix.alt_m)
        dec = self.cfg.declination_deg
        self.declination = (declination_rad(fix.lat_deg, fix.lon_deg, fix.alt_m, self.date or WMM_EPOCH)
                            if dec is None else math.radians(dec))
        self._heading_unset = self._last_mag is None and self.inertial is not False
        theta = None if self._last_mag is None else heading(*self._last_mag, self.declination)
        kept, f = self._learnt, self.cfg.filter
        b0, k0, d0 = (kept.b_psi, kept.k_s, kept.d) if kept else \
            (f.mag_offset_rad, f.slip_rad_per_mps2, f.sensors_ahead_m)
        x0 = initial_state(fix, theta, b0, k0, d0)
        self.ekf = NavEKF(f, x0)
        if kept:
            kept.restore(self.ekf)
        self.ekf.tilting(not self.ground)
        if self.inertial is False:
            self.ekf.hold_heading()
        self.t_us = self._started_us = fix.t_us
        if f.use_gnss_velocity and fix.vel_n_mps is not None:
            self.gnss_aid.held_course(fix)      # the first fix's course, which the next may repeat
        return [Notice(fix.t_us, "info", f"filter initialised at {fix.lat_deg:.6f}, {fix.lon_deg:.6f}")]

    # -- IMU ------------------------------------------------------------------------------------
    def _imu(self, s: ImuSample) -> list[Event]:
        events = self._imu_rate(s.t_us)
        if self._imu_unmeasured and self.ekf is not None:     # back after a silence (_imu_quiet)
            self._imu_unmeasured = False
            # the heading from the next compass reading, as at a start, but not from one whose alarm
            # stands (then as sure as it was held), nor while its test is near its threshold (then as
            # uncertain as at a start, the compass tested against it). What this leaves: a slow compass attack already
            # under way but calm when the IMU comes back is taken as the heading (README)
            trusted = Sensor.MAG not in self.health.excluded
            self.ekf.unmeasured(False, not self.ground, widen=trusted)
            calm = self.judge.ratios.get(Sensor.MAG, 0.0) < CALM_RATIO
            self._heading_unset = self.inertial is not False and trusted and calm
        if self._imu_silent:                        # back after a silence (_imu_quiet)
            since, self._imu_silent = self._imu_silent_since, False
            after = "" if since is None or s.t_us < since else f" after {(s.t_us - since) / 1e6:.1f} s"
            events.append(Notice(s.t_us, "info", f"IMU samples again{after}"))
        roll_pitch = self.tilt.at(s)
        ax, ay, rate, mag, tilt, tilt_rate = level(s, *roll_pitch)
        self._last_mag = mag
        events += self._compass(s.t_us, mag is not None)
        aside = self.inertial and self.ekf is not None and self._blow(s, events)
        # the heading's noise from its differences, without the declination (set at a filter's start: the
        # readings either side would differ by it)
        self.imu_aid.noise.add(s.t_us, ax, ay, rate, None if mag is None else heading(*mag, 0.0),
                               learn=not aside, calm=self.judge.calm)
        # the motors heard only in an IMU fast enough to integrate: at telemetry's 1 to 4 Hz the second
        # differences are the vehicle's own manoeuvres, and the watch said a start and a stop every
        # few seconds (43 lines on a real 10-minute flight) of a window no test used
        if self.imu_rate.fast is not False:
            events += self.motors.step(s.t_us, self.imu_aid.noise.vibration(), self.ekf)
        if self.imu_rate.fast:
            if aside:
                self.vertical.gap()
            else:
                events += self.vertical.imu(s, *roll_pitch)
        if aside:                                   # at any rate: at rest, a point is as good as a mean
            self.rest.gap()
        else:
            events += self.rest.imu(s)
        if self.inertial is False:
            if self.imu_rate.fast:                  # a slow stream's samples are points, not means
                self.manoeuvre.add(s.t_us, ax, ay, rate)
            # a stream first heard after guard went on GNSS alone without one (_imu_absent) is not slow
            # before its rate is known (RateWatch): its first samples are counted apart
            self.skipped["imu_no_compass" if self.compass.absent else
                         "imu_rate_unknown" if self.imu_rate.fast is None else "imu_too_slow"] += 1
            return events
        if self.ekf is None:
            self.skipped["imu_before_first_fix"] += 1
            return events
        if aside:
            self.skipped["imu_impact"] += 1
            return events
        due = self.averager.add(s.t_us, ax, ay, rate, mag, tilt, tilt_rate)
        if due is None:
            return events
        ax, ay, rate, mag, tilt, tilt_rate, n, n_mag = due
        motors_open = self.motors.open(s.t_us)     # as it stands after this sample's motors.step
        self.ekf.q[BM] = offset_q(self.cfg.filter.q_mag_offset_rad, motors_open, float(self.ekf.P[BM, BM])) ** 2
        self._advance(s.t_us)
        theta = None if mag is None else heading(*mag, self.declination)
        if theta is None and not self.compass.heard:   # a compass slower than the IMU is not one missing
            self.skipped["imu_no_magnetometer"] += 1
        elif theta is not None and self._heading_unset:     # the magnetometer's first word: the heading is its
            self.ekf.set_heading(math.remainder(theta - self.ekf.x[BM], math.tau))
            self._heading_unset = False
        aid, blocks, angle = self.imu_aid.measurement(self.ekf.x, theta, rate, ax, ay, self.ground, tilt,
                                                      tilt_rate, n, n_mag)
        r, S, PHT = self.ekf.innovation(aid.z, aid.hx, aid.H, aid.R, angle_rows=angle)
        events += self.noise_cap.step(s.t_us, self.imu_aid.measured[:3], self.imu_aid.floors[:3])
        if theta is not None:
            self.witnesses.add_heading(HeadingWitness(s.t_us, theta, rate))
        if self.ground:
            self.witnesses.add_side(s.t_us, rate, ay, float(self.ekf.x[VX]))
        # one stacked update, tested sensor by sensor; on wheels the constraint's row (the last) is tested
        # with the accelerometer's, whose sideways bias it shows first (the wheels hold the sideways
        # velocity the bias would build, and their constraint's innovation is where the bias goes)
        keep: list[int] = []
        lateral = self.ground and self.cfg.test_lateral
        for sensor, i, j in blocks:
            last = len(r) if lateral and sensor == Sensor.ACCEL else j     # the constraint's row follows the
                                                                            # accelerometer's
            # the compass's in a motors' window: its S holds the offset's fast walk, not the compass's noise
            ev, fused = self._test(sensor, s.t_us, r[i:last], S[i:last, i:last],
                                   modelled=sensor != Sensor.MAG or not motors_open)
            events += ev
            if fused:
                keep.extend(range(i, j))
        if self.ground:
            keep.append(len(r) - 1)                # a constraint, not a sensor: always fused
        self.history.imu_fused(s.t_us, fuse_rows(self.ekf, s.t_us, aid, r, S, PHT, keep, angle,
                                                 row_sensors(blocks, bool(self.ground))), self.ekf.x)
        if not self.ground:
            self.drift.imu(s.t_us, ax, ay, float(self.ekf.x[TH]))
        return events

    def _blow(self, s: ImuSample, events: list[Event]) -> bool:
        """Whether the IMU is set aside for a blow (guard.core.aiding.impact); the first of each filter's
        is said, and so is a run of them too long to be blows."""
        aside, dv_var = self.impact.check(s)
        if aside:
            self.averager.drop()                    # the samples before it, not to be averaged with those 0.5 s after
            self.drift.restart()                    # nor dead-reckoned through
            if dv_var > 0.0:
                self.ekf.blow(dv_var)
                self.history.blow(s.t_us, dv_var)
            if not self.impact.said:
                self.impact.said = True
                events.append(Notice(s.t_us, "info", f"a blow at the IMU ({self.impact.peak_g:.1f} g over "
                                     f"{MEAN_S * 1e3:g} ms: a landing, a crash, a kerb): its readings set aside "
                                     f"for {HOLD_S:g} s after each such mean over {IMPACT_G:g} g, the GNSS holding "
                                     "the estimate (counted as imu_impact)"))
        elif self.impact.overrun and not self.impact.overrun_said:
            self.impact.overrun_said = True
            events.append(Notice(s.t_us, "warning", f"the IMU's {MEAN_S * 1e3:g} ms means passed {IMPACT_G:g} g for "
                                 f"more than {BUDGET_S:g} s of {WINDOW_S:g} s: not blows; it is used and tested as "
                                 "it reads"))
        return aside

    def _compass(self, t_us: int, heard: bool) -> list[Event]:
        """An air vehicle without a compass is tested on its GNSS alone; one whose magnetometer speaks
        later has its IMU integrated again (guard.core.aiding.compass decides)."""
        verdict = self.compass.check(t_us, heard, self.ground, self.inertial)
        if verdict is None:
            return []
        if verdict in ("back", "ground") and self.imu_rate.fast is False:
            return []                       # a compass now, but an IMU still too slow to integrate
        if verdict == "back":
            self.inertial = True
            return self._reinitialise(t_us, "a magnetometer reading, after none: the IMU is integrated again")
        if verdict == "ground":
            self.inertial = True
            return self._reinitialise(t_us, "the autopilot reports a vehicle on wheels: its IMU is integrated again "
                                            "without a compass (its GNSS course witnesses the heading)")
        self.inertial = False
        if self.ekf is not None:
            self.ekf.hold_heading()
            self._heading_unset = False
        return [Notice(t_us, "warning", f"no magnetometer reading in {NO_COMPASS_S:g} s on an air vehicle: its heading "
                       "has no reference, the IMU is not integrated; GNSS position and velocity are tested "
                       "against each other alone (jumps, freezes, drifts)")]

    def _imu_rate(self, t_us: int) -> list[Event]:
        """An IMU stream slower than min_imu_hz (telemetry sends RAW_IMU at 1 to 4 Hz) cannot be
        integrated: GNSS position and velocity are then tested against each other alone, the heading
        held (said). One that comes faster later (guard asked the autopilot for more,
        guard.sources.rates) is integrated from then on, by a new filter. One that slows later is no
        longer integrated (RateWatch)."""
        judged = self.imu_rate.add(t_us)
        if judged is None:
            return []
        fast, hz, first = judged
        if fast:
            if first and self.inertial is False and self.ekf is not None:     # after none (_imu_absent)
                self.inertial = True
                return self._reinitialise(t_us, f"IMU at {hz:.1f} Hz, after none: integrated", keep_learnt=True)
            if first:
                self.inertial = True
                return []
            if self.inertial is not False or self.compass.absent:     # not integrated for want of a compass
                return []
            self.inertial = True
            return self._reinitialise(t_us, f"IMU now at {hz:.1f} Hz: integrated", keep_learnt=True)
        if self.inertial is False and not first:    # already not integrated (no compass)
            return []
        self.inertial = False
        if self.ekf is not None:
            self.ekf.hold_heading()
            self._heading_unset = False
        return [Notice(t_us, "warning", f"IMU {'at' if first else 'now at'} {hz:.1f} Hz, under "
                       f"{self.cfg.min_imu_hz:g} Hz: not integrated; GNSS position and velocity are tested against "
                       "each other alone (jumps, freezes, drifts)")]

    # -- testing and fusing -----------------------------------------------------------------------
    def _measure(self, sensor: Sensor, t_us: int, aid: Aid, modelled: bool = True) -> list[Event]:
        r, S, PHT = self.ekf.innovation(aid.z, aid.hx, aid.H, aid.R)
        events, fused = self._test(sensor, t_us, r, aid.tested(S), modelled)
        if fused:
            self.ekf.fuse(r, S, aid.H, aid.R, PHT)
        return events

    def _test(self, sensor: Sensor, t_us: int, r: np.ndarray, S: np.ndarray,
              modelled: bool = True) -> tuple[list[Event], bool]:
        """Test one innovation and learn from it. One whose variance was widened past the sensor's model
        (`modelled` False: a held course, the compass in a motors' window) is tested and fused, but the
        model's fit and the wander leave it out (its error is the course it repeats, or its S the
        offset's fast walk, not the sensor's noise; the wander's block being filled is dropped)."""
        events, fused = self.judge.test(sensor, t_us, r, S, self.ekf, self.t_us, self.gnss_index, self.record_tests,
                                        modelled)
        calm = self.ekf.learning = self.judge.calm      # nothing is learnt while a test is near its threshold
        if not modelled:
            if self.longrun is not None:
                self.longrun.interrupt(sensor)      # a block is not closed across it, with a gap in it
            return events, fused
        if fused:
            self.fit.add(sensor, t_us, r, S)
        if self.longrun is not None and fused and calm:
            said = self.longrun.add(sensor, t_us, r, S)
            if said:
                events.append(said)
        elif self.longrun is not None:
            self.longrun.interrupt(sensor)
        return events, fused
