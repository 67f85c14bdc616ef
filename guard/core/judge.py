"""Testing one sensor's innovation, and what follows: an alarm (named by the witnesses), the sensor's
exclusion and the rewind it owes, or, for an excluded sensor, its re-admission.

The judge owns no data but the time of the last GNSS velocity tested and of each sensor's last alarm
(whether a new one is a standing alarm going on); it reads the detector, the health record, the
witnesses and the history it is given, and the filter's state, and never calls the monitor back.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from guard.core.detectors import Detector
from guard.core.anchor import anchor
from guard.core.ekf import BAY, BM, BW, LA, TH, X, Y, NavEKF
from guard.core.health import Health
from guard.core.history import History
from guard.core.isolation import TURN_Z, Witnesses
from guard.core.longrun import LongRun
from guard.model.events import Alarm, Event, Innovation, Notice, Tested
from guard.model.samples import GnssFix
from guard.model.sensors import CHANNELS, RECEIVER, Sensor


CALM_RATIO = 0.5        # every test's statistic under this share of its threshold: the filter may learn
LATERAL_S = 1.0         # s: a "lateral" alarm comes within about a second of a sideways bias's onset, so its
                        # offset is read over the last second (over two, half of it would be from before)
STANDING_GAP_S = 30.0   # s: a latched sensor's alarm this soon after its last one is that one going on


class Judge:
    def __init__(self, cfg, detector: Detector, health: Health, witnesses: Witnesses, history: History,
                 longrun: LongRun | None = None):
        self.cfg = cfg                              # MonitorConfig
        self.detector, self.health, self.witnesses, self.history = detector, health, witnesses, history
        self.longrun = longrun                      # each test's scale for the wander of its innovations
        self.vel_t = -math.inf                      # time of the last GNSS velocity tested
        self.rewind_epochs = 0                      # what the last alarm asks the monitor to undo
        self.ratios: dict[Sensor, float] = {}       # each sensor's latest statistic / threshold, largest channel
        self.last_alarm: dict[Sensor, tuple[int, bool]] = {}   # sensor -> (time, standing) of its last alarm
        self.air = True                             # the vehicle may move sideways (the monitor says; on wheels
                                                    # the GNSS course witnesses the heading)

    @property
    def calm(self) -> bool:
        """No test near its threshold: what adapts to the vehicle (the compass offset b_psi, the IMU's
        measured noise) may adapt. A slow attack pushes some test's statistic up long before its alarm;
        while it does, nothing learns from it, so it cannot teach the filter to accept it."""
        return max(self.ratios.values(), default=0.0) < CALM_RATIO

    def test(self, sensor: Sensor, t_us: int, r: np.ndarray, S: np.ndarray, ekf: NavEKF, now_us: int,
             gnss_index: int, record: bool, modelled: bool = True) -> tuple[list[Event], bool]:
        """Run the detector on one sensor's innovation; decide whether to fuse it (`modelled`:
        Innovation's)."""
        stat, thr, hits = self.detector.test(sensor, t_us, r, self.longrun.scale(sensor, S) if self.longrun else S)
        self.ratios[sensor] = max([g / h for g, h in zip(stat, thr) if 0.0 < h < math.inf], default=0.0)
        if sensor == Sensor.GNSS_VEL:
            self.witnesses.last_vel = (r, S)    # the axis to name if a magnetometer alarm turns out to be it
            self.vel_t = t_us
        if sensor not in self.health.excluded:
            events = self._alarms(sensor, t_us, hits, stat, thr, ekf, now_us, gnss_index)
            fused = sensor not in self.health.excluded
        else:
            events, fused = self._readmission(sensor, t_us, r, S, hits, ekf, now_us, gnss_index)
        if record:
            innovation = Innovation(t_us, sensor, CHANNELS[sensor][:len(r)], r, S, fused, modelled)
            events.insert(0, Tested(innovation, gnss_index, stat, thr))
        return events, fused

    def _alarms(self, sensor, t_us, hits, stat, thr, ekf, now_us, gnss_index) -> list[Event]:
        """The alarms of a sensor in use: named (isolation), raised, and what it excludes."""
        events: list[Event] = []
        if not hits:                            # the usual case: nothing to name
            return events
        health, bw, run = self.health, ekf.x[BW], self._run(sensor)
        for i, offset in hits:
            lateral = sensor == Sensor.ACCEL and CHANNELS[sensor][i] == "lateral"
            named, ambiguous, channel = self.witnesses.isolate(sensor, now_us, bw, run) \
                if sensor in (Sensor.MAG, Sensor.GNSS_VEL) else self.witnesses.isolate_lateral(now_us, bw) \
                if lateral else (sensor, (), None)
            if named in health.excluded:
                continue
            channel = CHANNELS[sensor][i] if named == sensor else channel or CHANNELS[named][0]
            if named != sensor or lateral:      # a witness named it: its own offset, not the alarm's
                offset = self._witnessed(named, channel, lateral, bw, float(ekf.x[BAY]), float(ekf.x[LA]))
            events.append(Alarm(t_us, gnss_index, named, channel, stat[i], thr[i], offset,
                                self.detector.name, ambiguous, standing=self.record_alarm(named, t_us)))
            if not self.cfg.exclude_on_alarm:
                continue
            health.exclude(named, t_us, offset)
            if named in RECEIVER:
                # back to before the CUSUM's run began, its estimate of the onset; a velocity's run starts
                # late (a spoof's offset grows slowly and the filter absorbs it as an accelerometer
                # bias): back as far as the history goes
                self.rewind_epochs = self.detector.run_length.get(sensor, 0) \
                    if sensor == Sensor.GNSS_POS else len(self.history)
            if named == Sensor.MAG and Sensor.GYRO in ambiguous and self.air:
                # in the air the gyro's bias may as well be what turned apart from the compass: without the
                # compass the filter is to know it no better than at power-on, so that the GNSS course (as the
                # vehicle manoeuvres) finds it, or the heading's bounded life (reanchor_heading) gives the
                # compass back. (On wheels the course witnesses the heading all along.)
                forgotten = ekf.cfg.p0_gyro_bias_radps ** 2 - ekf.P[BW, BW]
                if forgotten > 0.0:
                    ekf.P[BW, BW] += forgotten
                # and agreeing with a heading held that loosely proves nothing (Health.blind, judged on the
                # heading's own uncertainty): the compass waits for the course, or for reanchor_heading
                health.size(Sensor.MAG, offset)
            if named == Sensor.MAG and sensor == Sensor.GNSS_VEL and run is not None:
                # the course named the compass over the alarm's run: the gyro bias the filter learnt from
                # it since the run began is the compass's turn, given back (as the accelerometer's below)
                ekf.x[BW] = run[1]
            if named == Sensor.ACCEL and (named != sensor or lateral):
                # the bias of the oldest epoch kept is taken for the sensor's own; what the filter
                # absorbed since is the attack's, given back
                oldest = self.history.oldest_x()
                health.accel_ref = float((oldest if oldest is not None else ekf.x)[BAY])
                ekf.x[BAY] = health.accel_ref
        return events

    def _witnessed(self, named: Sensor, channel: str, lateral: bool, bw: float, bay: float, ahead: float) -> float:
        """The offset of a sensor a witness named, in its own unit: the gyro's bias, the compass's turn,
        the GNSS velocity's innovation on its axis, the lateral accelerometer's mean reading less the
        centripetal acceleration and the sensors' swing (over the last LATERAL_S for a "lateral" alarm;
        the filter's bias where the accelerometer has no witness)."""
        w = self.witnesses
        if named == Sensor.GYRO:
            return w.gyro_bias()
        if named == Sensor.MAG:
            return w.turned
        if named == Sensor.GNSS_VEL:
            return float(w.last_vel[0][CHANNELS[named].index(channel)])
        if not w.side:
            return bay
        return w.lateral_bias(bw, LATERAL_S if lateral else 2.0, ahead)

    def _run(self, sensor: Sensor) -> tuple[int, float] | None:
        """A GNSS velocity alarm's run, to weigh the compass over: the time of the epoch it began at (one
        epoch per fix, as far back as the history goes) and the filter's gyro bias then. None for another
        sensor, or with the compass already excluded: no longer fused, it pulls nothing, and a GNSS
        velocity alarm then is the GNSS's (named the compass, it would be dropped as already excluded)."""
        n, epochs = self.detector.run_length.get(sensor, 0), self.history.epochs
        if sensor != Sensor.GNSS_VEL or n < 1 or not epochs or Sensor.MAG in self.health.excluded:
            return None
        epoch = epochs[-min(n, len(epochs))]
        return epoch.t_us, float(epoch.x[BW])

    def record_alarm(self, sensor: Sensor, t_us: int) -> bool:
        """Record an alarm on `sensor` at t_us (once per alarm: the judge's own and the freeze's), and
        say whether it is its standing alarm going on: the sensor is latched (fused again by a
        re-anchoring, never having agreed) and alarmed within STANDING_GAP_S before. Agreement cannot
        release a latch (an estimate anchored on the GNSS agrees with it by construction), so an alarm
        after a longer quiet is a new one."""
        last_t, _ = self.last_alarm.get(sensor, (None, False))
        standing = sensor in self.health.latched and last_t is not None and \
            0 <= t_us - last_t <= STANDING_GAP_S * 1e6
        self.last_alarm[sensor] = (t_us, standing)
        return standing

    def _readmission(self, sensor, t_us, r, S, hits, ekf, now_us, gnss_index) -> tuple[list[Event], bool]:
        """An excluded sensor's test: re-admitted once it has agreed long enough and no witness holds it,
        or, the compass, once the heading cannot be held without it (reanchor_heading)."""
        if sensor == Sensor.MAG:
            sigma = self._heading_sigma(ekf)        # what the estimate could see of the compass's offset
            if sensor not in self.health.with_receiver:
                events = self.reanchor_heading(sigma, t_us, gnss_index)
                if events:
                    return events, True
        else:
            sigma = math.sqrt(float(np.max(np.diagonal(S))))
        z = np.abs(r) / np.sqrt(np.diagonal(S))
        bad = bool(hits) or bool(np.any(z > self.cfg.readmit_sigma)) or \
            self.health.blind(sensor, sigma, self.cfg.readmit_sigma) or \
            self._held(sensor, t_us, ekf, now_us)
        if not self.health.settle(sensor, t_us, bad):
            return [], False
        events = self.readmit(sensor, t_us, gnss_index)
        if sensor == Sensor.GNSS_POS and Sensor.GNSS_VEL in self.health.excluded:
            events += self.readmit(Sensor.GNSS_VEL, t_us, gnss_index)   # fixes without a velocity: back with it
        return events, True

    def _held(self, sensor: Sensor, t_us: int, ekf: NavEKF, now_us: int) -> bool:
        """A witness still holds an excluded sensor whose own innovation agrees."""
        bw, witnesses = ekf.x[BW], self.witnesses
        if sensor == Sensor.GYRO:               # its heading still turns away from the magnetometer's
            return abs((witnesses.turns(now_us, bw) or (0.0,))[0]) >= TURN_Z[1]
        if sensor == Sensor.ACCEL:              # it still reads sideways what the wheels do not do
            ref = self.health.accel_ref
            return ref is not None and witnesses.fresh(t_us) and \
                abs(witnesses.lateral_bias(bw, ahead=float(ekf.x[LA])) - ref) >= self.cfg.filter.accel_sigma_mps2
        if sensor == Sensor.GNSS_POS:
            # a receiver whose velocity is still judged attacked: its position waits. (The filter's own
            # uncertainty grows while both are out, which would let a spoofed position "agree".)
            return Sensor.GNSS_VEL in self.health.excluded and t_us - self.vel_t < 1e6
        return False

    def readmit(self, sensor: Sensor, t_us: int, gnss_index: int, silent: bool = False) -> list[Event]:
        self.detector.forget(sensor)                # a fresh test: what it summed while excluded is spent
        return self.health.readmit(sensor, t_us, gnss_index, silent)

    def reanchor(self, ekf: NavEKF, fix: GnssFix, en: tuple[float, float], gnss_aid, max_coast_m: float,
                 gnss_index: int, widen: Callable[[float], float] | None = None, held: bool = False,
                 gnss_only: bool = False) -> list[Event]:
        """An exclusion has a bounded life: once the other sensors cannot hold the estimate to within
        max_coast_m (1 sigma), the GNSS can be neither confirmed nor refuted; the estimate is
        re-anchored on it, and its alarm stands (latched, no Cleared). What a patient attacker gains:
        an offset that grew slowly enough to be excluded, held out for that long, is then taken.
        Asked at each fix while the GNSS is out, and at once after an alarm's rewind (Monitor.finish),
        whose estimate may already be beyond holding (GNSS alone: nothing else held it). `widen`: the
        filter's uncertainty as far as the drift measured on this vehicle makes it (guard.core.drift). `held`:
        the fix's course was held by its receiver (GnssAiding.held_course), its velocity's direction unknown.
        `gnss_only`: the GNSS is tested alone (no IMU integrated): with its position and velocity both
        set aside nothing else holds the estimate, and the line says so rather than a figure of the
        random walk's (thousands of metres after a rewind) that means nothing to an operator."""
        filtered = math.sqrt(ekf.P[X, X] + ekf.P[Y, Y])
        sigma = filtered if widen is None else widen(filtered)
        if sigma <= max_coast_m:
            return []
        anchor(ekf, fix, en, gnss_aid.sigma_pos(fix), gnss_aid.sigma_vel(fix, held), self.history.delay_s)
        at_fix = ekf.x.copy()                       # the anchor where the fix shows the vehicle
        at_fix[X], at_fix[Y] = en
        self.history.anchored(fix.t_us, at_fix)
        # said as a warning once per alarm: for a standing alarm going on (each sensor excluded by an alarm
        # of its own is), it is the same news
        own = [s for s in RECEIVER if s in self.health.excluded and s not in self.health.with_receiver]
        again = bool(own) and all(self.last_alarm.get(s, (0, False))[1] for s in own)
        nothing = gnss_only and all(s in self.health.excluded for s in RECEIVER)
        why = ("tested alone, nothing else holds the estimate" if nothing else
               f"the estimate +-{sigma:.0f} m without it"
               f"{', as far as its IMU drifts in this flight' if sigma > filtered else ''}")
        events: list[Event] = [Notice(fix.t_us, "info" if again else "warning", f"GNSS could not be confirmed "
                                      f"or refuted ({why}): re-anchored on it"
                                      f"{' again' if again else ''}, its alarm stands")]
        for sensor in [s for s in RECEIVER if s in self.health.excluded]:
            events += self.readmit(sensor, fix.t_us, gnss_index, silent=True)
        return events

    def reanchor_heading(self, sigma: float, t_us: int, gnss_index: int) -> list[Event]:
        """The compass's exclusion has a bounded life too. Once the heading held without it (by the gyro,
        and by the GNSS course while the vehicle manoeuvres) is uncertain by more than
        max_coast_heading_deg (1 sigma: an air vehicle hovering on a gyro whose bias is known only so
        well), the compass can be neither confirmed nor refuted: it is fused again, its reading
        re-anchoring the heading (whose variance is by then mostly the filter's), and its alarm stands
        (latched, no Cleared). What a patient attacker gains: a compass turned and held out that long
        is then taken. While the GNSS course holds the heading (on wheels, or in the air as the vehicle
        turns and speeds up) the heading stays sure and the compass refuted. `sigma`: the heading's
        uncertainty without it (_heading_sigma); past pi (the gyro excluded as well, the yaw rate a random
        walk) the line says the heading is unknown rather than a figure of thousands of degrees."""
        if sigma <= math.radians(self.cfg.max_coast_heading_deg):
            return []
        again = self.last_alarm.get(Sensor.MAG, (0, False))[1]
        # past a half turn a figure means nothing (the gyro set aside too: nothing holds the heading)
        why = f"heading +-{math.degrees(sigma):.0f} deg" if sigma <= math.pi else "heading unknown"
        return [Notice(t_us, "info" if again else "warning", f"compass could not be confirmed or refuted (the "
                       f"{why} without it): re-anchored on it"
                       f"{' again' if again else ''}, its alarm stands")] + \
            self.readmit(Sensor.MAG, t_us, gnss_index, silent=True)

    @staticmethod
    def _heading_sigma(ekf: NavEKF) -> float:
        """How sure the estimate is of what the compass should read, theta + b_psi (rad, 1 sigma)."""
        P = ekf.P
        return math.sqrt(max(P[TH, TH] + P[BM, BM] + 2.0 * P[TH, BM], 0.0))
