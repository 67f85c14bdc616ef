"""The core on real vehicles' streams as they come: a compass that is slow, late or absent, a receiver
read by its HDOP or still finding itself, IMU streams that change rate, the motors' vibration, a vehicle
whose type is not said (beside test_real_vehicle.py: the suite's workers take a file each)."""

import copy
import dataclasses
import math

import numpy as np
import pytest

from guard.core.ekf import FilterConfig
from guard.core.monitor import MonitorConfig
from guard.model.events import Alarm, Estimate, Notice
from guard.model.samples import GnssFix, VehicleType
from unit.synthetic import T0_US, drive, of, run

GROUND = MonitorConfig(declination_deg=0.0, vehicle="ground")
AIR = MonitorConfig(declination_deg=0.0, vehicle="air")


def _slow_compass(samples, every, sigma_deg, seed, repeated=False):
    """A compass read every `every` IMU samples, each reading off by its own noise of sigma_deg, on
    the first IMU sample after it (as the sources give it) or, `repeated`, on every sample until the
    next (as they gave it before: one reading counted `every` times)."""
    rng = np.random.default_rng(seed)
    out, held, k = [], None, 0
    for s in samples:
        if isinstance(s, GnssFix):
            out.append(s)
            continue
        fresh = held is None or k % every == 0
        k += 1
        if fresh:
            a = math.radians(rng.normal(0.0, sigma_deg))
            c, sn = math.cos(a), math.sin(a)
            held = (c * s.mag_x_gauss - sn * s.mag_y_gauss, sn * s.mag_x_gauss + c * s.mag_y_gauss, s.mag_z_gauss)
        m = held if fresh or repeated else (None, None, None)
        out.append(dataclasses.replace(s, mag_x_gauss=m[0], mag_y_gauss=m[1], mag_z_gauss=m[2]))
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_slow_compass_is_one_measurement_per_reading(seed, runs):
    """A 2 Hz compass with 2 degrees of noise per reading among 50 Hz IMU samples: one measurement
    per reading, it never alarms, and a 15 degree turn of it at 120 s is caught within 2 s. Counted on
    every IMU sample until the next reading (what the log sources did), each error counts 25 times
    and it alarmed within seconds."""
    base = drive(180.0, yaw=0.4, seed=seed)
    _, events = runs.run(_slow_compass(base, 25, 2.0, seed), GROUND, at_us=(T0_US + 120_000_000,))
    assert [a for a in of(events, Alarm) if a.sensor == "mag"] == []
    _, events = run(_slow_compass(base, 25, 2.0, seed, repeated=True), GROUND)
    assert [a for a in of(events, Alarm) if a.sensor == "mag"]
    k = next(i for i, s in enumerate(base) if s.t_us >= T0_US + 120_000_000)
    turned = drive(180.0, yaw=0.4, seed=seed, mag_offset_deg=15.0)
    _, events = runs.run(_slow_compass(base[:k] + turned[k:], 25, 2.0, seed), GROUND)     # the first 120 s: once
    after = [a for a in of(events, Alarm) if a.t_us >= T0_US + 120_000_000]
    assert after and after[0].sensor == "mag" and after[0].t_us - (T0_US + 120_000_000) < 2_000_000, after[:1]


def test_an_air_vehicle_without_a_compass_is_tested_on_its_gnss_alone_and_says_so():
    """No magnetometer reading at all (none fitted, or one that reads zeros): after 10 s of IMU an
    air vehicle's IMU is not integrated (its heading has no reference), said once; clean, it is quiet;
    a 10 m step on the GNSS still alarms at once."""
    samples = drive(120.0, yaw=0.4, seed=13, mag=lambda t: False,
                    gnss_offset=lambda t: (0.0, 10.0 if t >= 90.0 else 0.0))
    mon, events = run(samples, AIR)
    said = [n for n in of(events, Notice) if "no magnetometer reading" in n.text]
    assert len(said) == 1 and said[0].level == "warning" and mon.inertial is False
    assert mon.skipped["imu_no_compass"] > 0 and "imu_too_slow" not in mon.skipped, mon.skipped   # said as it is
    alarm, *_ = of(events, Alarm)
    assert (alarm.sensor, alarm.channel) == ("gnss_pos", "north") and alarm.t_us - (T0_US + 90_000_000) < 250_000


def test_a_ground_vehicle_without_a_compass_keeps_its_imu():
    """On wheels the GNSS course witnesses the heading: the IMU stays integrated, nothing is said."""
    mon, events = run(drive(60.0, yaw=0.4, seed=14, mag=lambda t: False), GROUND)
    assert mon.inertial is True and not [n for n in of(events, Notice) if "no magnetometer" in n.text]
    assert of(events, Alarm) == []


def test_a_late_word_that_the_vehicle_is_on_wheels_gives_its_imu_back():
    """An "auto" vehicle without a compass whose autopilot says "ground" only after its IMU was set aside
    (a link joined late, a HEARTBEAT lost): the IMU is integrated again, as a ground vehicle's would have
    been from the start, said once; nothing alarms and no sample after it is set aside for want of a compass."""
    samples = drive(60.0, yaw=0.4, seed=14, mag=lambda t: False)
    k = next(i for i, s in enumerate(samples) if s.t_us >= T0_US + 20_000_000)
    mon, events = run(samples[:k] + [VehicleType(ground=True)] + samples[k:], MonitorConfig(declination_deg=0.0))
    said = [n.text for n in of(events, Notice) if "no magnetometer reading" in n.text or "on wheels" in n.text]
    assert len(said) == 2 and "on wheels" in said[1], said
    assert mon.inertial is True and of(events, Alarm) == []
    n_aside = mon.skipped["imu_no_compass"]
    assert 0 < n_aside <= 11 * 50, n_aside        # from 10 s to 20 s only, at 50 Hz


def test_a_receiver_that_reports_only_its_hdop_is_trusted_by_it():
    """Position noise with no h_acc: gnss_pos_unreported_m per unit of HDOP (0.5 m at HDOP 1, the
    default's level), within the floor and the cap; its random walk q_pos_m per unit of HDOP."""
    from guard.core.aiding.gnss import GnssAiding
    f = FilterConfig()
    aid = GnssAiding(f)
    fix = GnssFix(T0_US, True, 0.0, 0.0, 0.0, None, None, None, None)
    assert aid.sigma_pos(fix) == f.gnss_pos_unreported_m
    assert aid.sigma_pos(dataclasses.replace(fix, hdop=1.0)) == pytest.approx(f.gnss_pos_unreported_m)
    assert aid.sigma_pos(dataclasses.replace(fix, hdop=2.0)) == pytest.approx(2 * f.gnss_pos_unreported_m)
    assert aid.sigma_pos(dataclasses.replace(fix, hdop=0.3)) == f.gnss_pos_sigma_m
    assert aid.sigma_pos(dataclasses.replace(fix, hdop=40.0)) == pytest.approx(10 * f.gnss_pos_sigma_m)
    assert aid.sigma_pos(dataclasses.replace(fix, h_acc_m=1.0, hdop=3.0)) == pytest.approx(0.4)   # h_acc first
    # and the correlated error the estimate follows, per unit of HDOP, never below the default's
    assert aid.q_pos(fix) == aid.q_pos(dataclasses.replace(fix, hdop=0.6)) == f.q_pos_m
    assert aid.q_pos(dataclasses.replace(fix, hdop=2.0)) == pytest.approx(2 * f.q_pos_m)
    assert aid.q_pos(dataclasses.replace(fix, h_acc_m=1.0, hdop=2.0)) == f.q_pos_m


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_older_receiver_wandering_at_its_hdop_is_quiet_and_a_step_still_caught(seed, runs):
    """A receiver with no h_acc at HDOP 2 whose position wanders against its own velocity by about a
    metre over tens of seconds (the Erle PXF flights' receivers): read by its HDOP it is quiet, its
    test's largest statistic well under the one it reaches read as an unreported receiver (HDOP 1),
    where it alarms on two seeds of three; a 10 m step is caught at once."""
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0.0, 0.12, (3001, 2)), axis=0)     # m, one step per 0.2 s fix
    walk -= np.linspace(0, 1, 3001)[:, None] * walk[-1]             # a wander, not a drift
    def wander(t, step=0.0):
        i = min(int(t / 0.2), 3000)
        return walk[i, 0], walk[i, 1] + step
    clean = drive(600.0, yaw=0.4, seed=seed, gnss_offset=wander, vel_acc=None, h_acc=None)
    with_hdop = [dataclasses.replace(s, hdop=2.0) if isinstance(s, GnssFix) else s for s in clean]
    mon, events = runs.run(with_hdop, GROUND, at_us=(T0_US + 300_000_000,))
    assert [a for a in of(events, Alarm) if a.sensor == "gnss_pos"] == []
    read_by_hdop = mon.detector.peak["gnss_pos"]
    mon, events = run(clean, GROUND)
    assert read_by_hdop < 0.75 * mon.detector.peak["gnss_pos"], (read_by_hdop, mon.detector.peak["gnss_pos"])
    stepped = drive(310.0, yaw=0.4, seed=seed, vel_acc=None, h_acc=None,      # the same wander to 310 s
                    gnss_offset=lambda t: wander(t, 10.0 if t >= 300.0 else 0.0))
    _, events = runs.run([dataclasses.replace(s, hdop=2.0) if isinstance(s, GnssFix) else s for s in stepped],
                         GROUND)                                 # its first 300 s those of the run above: once
    after = [a for a in of(events, Alarm) if a.t_us >= T0_US + 300_000_000]
    assert after and after[0].sensor == "gnss_pos" and after[0].t_us - (T0_US + 300_000_000) < 400_000, after[:1]


def test_a_compass_that_starts_late_gives_the_heading_back():
    """No magnetometer for the first 30 s of an air vehicle's IMU, then one: set aside at 10 s (said),
    then the filter starts again with its IMU integrated (said), quiet, and a 10 m step caught."""
    samples = drive(120.0, yaw=0.4, seed=15, mag=lambda t: t >= 30.0,
                    gnss_offset=lambda t: (0.0, 10.0 if t >= 90.0 else 0.0))
    mon, events = run(samples, AIR)
    notes = [n.text for n in of(events, Notice) if "magnetometer" in n.text]
    assert len(notes) == 2 and notes[0].startswith("no magnetometer reading in 10 s") and \
        notes[1].startswith("a magnetometer reading, after none"), notes
    assert mon.inertial is True
    alarm, *_ = of(events, Alarm)
    assert (alarm.sensor, alarm.channel) == ("gnss_pos", "north") and alarm.t_us - (T0_US + 90_000_000) < 250_000


@pytest.mark.parametrize("seed", [16, 17, 18])
def test_on_gnss_alone_an_alarm_never_leaves_the_estimate_coasting_away(seed):
    """An air vehicle without a compass (GNSS position and velocity tested against each other alone)
    whose GNSS north drifts at 0.2 m/s: the CUSUM's run, its estimate of the onset, is long, and the
    rewind to before it leaves an estimate that nothing but the GNSS held over that time (hundreds of
    metres, 1 sigma). The alarm epoch's own fix is then the anchor at once, said with the alarm and
    the alarm standing: every estimate published stays within a few metres of its fix (before, the
    next ones coasted 28 to 42 m away)."""
    samples = drive(120.0, yaw=0.4, seed=seed, mag=lambda t: False,
                    gnss_offset=lambda t: (0.0, 0.2 * (t - 60.0) if t >= 60.0 else 0.0))
    mon, events = run(samples, AIR)
    alarm, *_ = of(events, Alarm)
    assert alarm.sensor == "gnss_pos" and alarm.t_us >= T0_US + 60_000_000
    said = [n for n in of(events, Notice) if "re-anchored" in n.text]
    assert said and said[0].t_us == alarm.t_us, [(n.t_us, n.text) for n in of(events, Notice)]
    # on GNSS alone nothing else held it: said so, not as the random walk's thousands of metres
    assert "(tested alone, nothing else holds the estimate)" in said[0].text and "+-" not in said[0].text, said[0].text
    estimates = of(events, Estimate)
    assert all(e.fix_en is not None for e in estimates)
    far = max(math.hypot(e.east_m - e.fix_en[0], e.north_m - e.fix_en[1]) for e in estimates)
    assert far < 5.0, far
    assert "gnss_pos" in mon.alarmed


@pytest.mark.parametrize("seed", [20, 21])
def test_a_receiver_still_finding_itself_is_not_started_on(seed, monkeypatch):
    """For its first 15 s a receiver says its fixes are good to 20 m, and they lie 8 m north of where
    it then settles (a real u-blox after its first fix: 47, 22, 11 m, its solution converging):
    monitoring waits for a fix it calls good to 5 m, says so once and counts what it skipped, and
    raises no alarm. Started on the coarse fixes, the settling is a GNSS step where the receiver's 20 m
    is taken only up to the fixed cap; taken at its word from the start (its usual figure, heard while
    nothing was tested: guard.core.aiding.receiver), the filter follows it there too."""
    import pymap3d
    def coarse(s):
        if not isinstance(s, GnssFix) or s.t_us >= T0_US + 15_000_000:
            return s
        lat, lon, _ = pymap3d.enu2geodetic(0.0, 8.0, 0.0, s.lat_deg, s.lon_deg, 0.0)
        return dataclasses.replace(s, lat_deg=float(lat), lon_deg=float(lon), h_acc_m=20.0)
    samples = [coarse(s) for s in drive(90.0, yaw=0.4, seed=seed)]
    mon, events = run(samples, GROUND)
    assert of(events, Alarm) == []
    said = [n for n in of(events, Notice) if "only: monitoring starts once" in n.text]
    assert len(said) == 1 and "20 m" in said[0].text, [n.text for n in of(events, Notice)]
    assert mon.skipped["gnss_coarse_before_start"] == 15 * 5
    started = [n for n in of(events, Notice) if n.text.startswith("filter initialised")]
    assert started[0].t_us >= T0_US + 15_000_000
    from guard.core.aiding import gnss
    monkeypatch.setattr(gnss, "START_H_ACC_M", 1e9)               # as before: started on the first fix
    assert not of(run(samples, GROUND)[1], Alarm)
    monkeypatch.setattr("guard.core.aiding.receiver.LEVEL_FACTOR", 0.0)     # and the 20 m capped
    events = run(samples, GROUND)[1]
    assert [a for a in of(events, Alarm) if a.sensor == "gnss_pos"], "started on the coarse fixes, no alarm?"


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_imu_stream_that_comes_faster_later_is_integrated_from_then_on(seed):
    """Telemetry at 1 Hz until the autopilot is asked for more (guard.sources.rates), then 50 Hz: GNSS
    alone first, said once; then a new filter that integrates the IMU, said once, no alarm; and the
    IMU is really integrated: a gyro bias from 90 s is caught, on the heading."""
    from guard.model.samples import ImuSample
    bias = (lambda t: 0.05 if t >= 90.0 else 0.0)
    samples = [s for s in drive(120.0, seed=seed, yaw=0.3, gyro_bias=bias)
               if not (isinstance(s, ImuSample) and s.t_us < T0_US + 20_000_000 and (s.t_us - T0_US) % 1_000_000)]
    mon, events = run(samples, GROUND)
    texts = [e.text for e in of(events, Notice)]
    assert sum("not integrated" in t for t in texts) == 1, texts
    assert sum("IMU now at 50.0 Hz: integrated" in t for t in texts) == 1, texts
    assert mon.inertial is True and 15 <= mon.skipped["imu_too_slow"] <= 25, mon.skipped
    alarms = of(events, Alarm)
    assert alarms and alarms[0].t_us >= T0_US + 90_000_000 and alarms[0].sensor in ("gyro", "mag"), alarms[:2]
    assert alarms[0].t_us - (T0_US + 90_000_000) < 3_000_000


@pytest.mark.parametrize("seed, speed", [(1, 8.0), (2, 8.0), (3, 20.0), (4, 30.0)])
def test_a_late_receiver_re_anchored_on_is_followed_not_alarmed_on_again(seed, speed):
    """A receiver whose fixes show the vehicle 0.2 s before their stamp, modelled (gnss_delay_s), on an
    air vehicle that cannot hold a 10 m step out for long (max_coast_m 1): one alarm, one re-anchoring
    on the stepped GNSS, and from then on the estimate follows it. The late fixes are compared with the
    filter's stored states: kept from before the anchor (the estimate that could not be held), the
    next fix met them and alarmed again at once, and the re-anchoring went round again and again."""
    lag, yaw = 0.2, 0.3
    late = (-speed * math.cos(yaw) * lag, -speed * math.sin(yaw) * lag)     # where the vehicle was lag ago
    cfg = MonitorConfig(declination_deg=0.0, vehicle="air", max_coast_m=1.0, filter=FilterConfig(gnss_delay_s=lag))
    samples = drive(90.0, speed=speed, yaw=yaw, seed=seed,
                    gnss_offset=lambda t: (late[0], late[1] + (10.0 if t >= 30.0 else 0.0)))
    mon, events = run(samples, cfg)
    alarms = of(events, Alarm)
    anchors = [e for e in of(events, Notice) if "re-anchored" in e.text]
    assert [(a.sensor, a.channel) for a in alarms] == [("gnss_pos", "north")], alarms
    assert abs(alarms[0].t_us - (T0_US + 30_000_000)) <= 200_000
    assert len(anchors) == 1, [(e.t_us, e.text) for e in anchors]
    last = of(events, Estimate)[-1]
    assert math.hypot(last.east_m - last.fix_en[0] + late[0], last.north_m - last.fix_en[1] + late[1]) < 1.0


@pytest.mark.parametrize("seed", [1, 2])
def test_an_imu_stream_that_slows_later_is_no_longer_integrated_until_it_comes_back(seed):
    """50 Hz, then 5 Hz from 40 to 70 s (a ground station on the same port lowered it), then 50 Hz:
    integrated, then GNSS alone (said), then integrated again by a new filter (said); a gap of one
    sample is none of these, nor a lossy link's dropped samples; and no alarm."""
    from guard.model.samples import ImuSample
    lossy = np.random.default_rng(seed)

    def kept(s) -> bool:
        t = (s.t_us - T0_US) / 1e6
        if not isinstance(s, ImuSample):
            return True
        if 20.0 < t < 20.5:                 # a 0.5 s gap: one long interval
            return False
        if 5.0 < t < 15.0 and lossy.random() < 0.65:     # a lossy link: runs of drops, some over 125 ms
            return False
        return not (40.0 <= t < 70.0) or (s.t_us - T0_US) % 200_000 == 0
    mon, events = run([s for s in drive(100.0, seed=seed, yaw=0.3) if kept(s)], GROUND)
    texts = [(round((e.t_us - T0_US) / 1e6), e.text) for e in of(events, Notice)]
    slowed = [t for t, text in texts if "IMU now at 5.0 Hz, under 8 Hz: not integrated" in text]
    back = [t for t, text in texts if "IMU now at 50.0 Hz: integrated" in text]
    assert len(slowed) == 1 and 40 <= slowed[0] <= 45, texts      # 20 slow intervals in a row: 4 s
    assert len(back) == 1 and 70 <= back[0] <= 71, texts
    assert not any("under 8 Hz" in text for t, text in texts if t < 40), texts
    assert 120 <= mon.skipped["imu_too_slow"] <= 150 and mon.inertial is True, mon.skipped
    assert of(events, Alarm) == []


def test_a_compass_that_speaks_late_does_not_integrate_an_imu_too_slow():
    """An air vehicle without a magnetometer reading (its IMU set aside at 10 s), whose IMU slows to
    2 Hz at 30 s; the magnetometer speaks at 50 s: the 2 Hz IMU is still not integrated. At 50 Hz
    again from 70 s, it is, by a new filter."""
    from guard.model.samples import ImuSample

    def kept(s) -> bool:
        t = (s.t_us - T0_US) / 1e6
        return not isinstance(s, ImuSample) or not (30.0 <= t < 70.0) or (s.t_us - T0_US) % 500_000 == 0
    samples = [s for s in drive(100.0, seed=5, yaw=0.3, mag=lambda t: t >= 50.0) if kept(s)]
    mon, events = run(samples, MonitorConfig(declination_deg=0.0, vehicle="air"))
    texts = [(round((e.t_us - T0_US) / 1e6), e.text) for e in of(events, Notice)]
    assert not any("integrated again" in text for _, text in texts), texts
    back = [t for t, text in texts if "IMU now at 50.0 Hz: integrated" in text]
    assert len(back) == 1 and 70 <= back[0] <= 71, texts
    assert mon.inertial is True and of(events, Alarm) == []


@pytest.mark.parametrize("vehicle", ["ground", "air"])
@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_motors_spinning_up_are_a_vibration_not_an_accelerometer_attack(vehicle, seed, runs):
    """A copter's motors spin up: within a sample, its accelerometers' noise goes from 0.03 m/s^2 to
    1 m/s^2 (the lift-off alarms of real flights). The noise is measured at once, and nothing alarms
    (on the code before, 3 of 4 such runs raised an accelerometer alarm within 0.4 s)."""
    samples = drive(60.0, seed=seed, vibration=lambda t: 1.0 if t >= 30.0 else 0.0)
    mon, events = runs.run(samples, MonitorConfig(declination_deg=0.0, vehicle=vehicle),   # the tests below
                           at_us=(T0_US + 30_000_000, T0_US + 45_000_000))                 # go on from here
    assert of(events, Alarm) == []


@pytest.mark.parametrize("vehicle", ["ground", "air"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_accelerometer_bias_under_that_vibration_is_still_caught(vehicle, seed, runs):
    """The same vibration from 30 s, and a 0.5 m/s^2 bias on the forward accelerometer from 45 s:
    caught within 10 s (4 to 7 s: the bias is half the vibration; 1.4 to 2 s without it), nothing
    before."""
    samples = drive(70.0, seed=seed, vibration=lambda t: 1.0 if t >= 30.0 else 0.0,
                    accel_bias=lambda t: 0.5 if t >= 45.0 else 0.0)
    mon, events = runs.run(samples, MonitorConfig(declination_deg=0.0, vehicle=vehicle))
    alarms = of(events, Alarm)
    assert alarms and 0 <= alarms[0].t_us - (T0_US + 45_000_000) <= 10_000_000, alarms[:1]


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_a_bias_written_with_a_jitter_is_caught_as_a_bias_under_a_vibration(seed, runs):
    """What the short memory gives up: an attacker writes 1.5 m/s^2 of jitter into the accelerometers and
    0.5 m/s^2 of bias into the forward one at the same instant. The jitter is no longer an alarm by
    itself (as a motor start is not); the bias is caught within 10 s (0.1 to 7.6 s on these seeds,
    where the code before alarmed at the jitter's onset, within 0.3 s, in 4 of 5)."""
    samples = drive(60.0, seed=seed, vibration=lambda t: 1.5 if t >= 30.0 else 0.0,
                    accel_bias=lambda t: 0.5 if t >= 30.0 else 0.0)
    mon, events = runs.run(samples, GROUND)
    alarms = of(events, Alarm)
    assert alarms and 0 <= alarms[0].t_us - (T0_US + 30_000_000) <= 10_000_000, alarms[:1]


def test_the_short_memory_sees_a_vibration_at_once_and_not_a_bias_step_or_a_ramp():
    """The IMU's measured noise (guard.core.aiding.imu.ImuNoise) while a test is near its threshold
    (calm False: the slow memory learns nothing), over 200 seeds: white noise of 1 m/s^2 is seen
    within NOISE_SHORT + 1 samples (read low, at about two thirds, by design: a median of squares);
    a 2 m/s^2 step, or a ramp of 1 m/s^2 per second, leave the floor where it was, and so does a jump
    across a gap."""
    from guard.core.aiding.imu import NOISE_SHORT, ImuNoise
    floors = (0.15, 0.15, 0.01, 0.03)

    def fed(values, gap_at=None):
        noise = ImuNoise()
        for k, a in enumerate(values):
            t = T0_US + 20_000 * k + (1_000_000 if gap_at is not None and k >= gap_at else 0)
            noise.add(t, a, 0.0, 0.0, None, calm=k < 50)
        return noise.sigmas(floors, 1)[0]
    read, steps, ramps = [], [], []
    for seed in range(200):
        rng = np.random.default_rng(seed)
        quiet = list(rng.normal(0.0, 0.03, 50))
        read.append(fed(quiet + list(rng.normal(0.0, 1.0, NOISE_SHORT + 1))))
        steps.append(fed(quiet + list(2.0 + rng.normal(0.0, 0.03, 20))))
        ramps.append(fed(quiet + list(0.02 * np.arange(1, 60) + rng.normal(0.0, 0.03, 59))))
    assert 0.5 < float(np.median(read)) < 1.0 and np.mean(np.array(read) > 0.3) > 0.85, np.percentile(read, [5, 50])
    assert max(steps) == 0.15 and max(ramps) == 0.15, (max(steps), max(ramps))
    # a gap: the jump across it is not a difference, first or second
    rng = np.random.default_rng(1)
    assert fed(list(rng.normal(0.0, 0.03, 50)) + list(3.0 + rng.normal(0.0, 0.03, 10)), gap_at=50) == 0.15


@pytest.mark.parametrize("told_at_s", [None, 5.0])
def test_auto_without_the_vehicle_type_is_said_once(told_at_s):
    """`monitor.vehicle = "auto"` and a source that never says what the vehicle is (DroneCAN, a log
    without the autopilot's HEARTBEAT): after 10 s of monitoring a WARNING names the key, once; a
    HEARTBEAT before then (told_at_s), or a config that names the vehicle, says nothing."""
    samples = drive(40.0, seed=3)
    if told_at_s is not None:
        k = next(i for i, s in enumerate(samples) if s.t_us >= T0_US + int(told_at_s * 1e6))
        samples = samples[:k] + [VehicleType(ground=False)] + samples[k:]
    _, events = run(samples, MonitorConfig(declination_deg=0.0))
    said = [n for n in of(events, Notice) if "monitor.vehicle" in n.text]
    if told_at_s is None:
        assert len(said) == 1 and said[0].level == "warning", said
        assert 10.0 <= (said[0].t_us - T0_US) / 1e6 <= 10.5
        assert '"ground"' in said[0].text
    else:
        assert said == []
    _, events = run(drive(40.0, seed=3), GROUND)
    assert [n for n in of(events, Notice) if "monitor.vehicle" in n.text] == []


def test_the_wait_for_the_vehicle_type_starts_again_with_a_new_filter():
    """A clock that jumps a minute ahead re-initialises the filter: the 10 s of monitoring before the
    vehicle's type is said missing are counted from the new filter, not from the old clock."""
    samples = drive(40.0, seed=3)
    jump = T0_US + 3_000_000
    samples = [dataclasses.replace(s, t_us=s.t_us + 60_000_000) if s.t_us >= jump else s for s in samples]
    _, events = run(samples, MonitorConfig(declination_deg=0.0))
    again = next(n.t_us for n in of(events, Notice) if "re-initialised" in n.text)
    said = [n for n in of(events, Notice) if "monitor.vehicle" in n.text]
    assert len(said) == 1 and said[0].t_us - again >= 9_500_000, (said, again)


def test_the_fit_check_judges_the_sideways_constraint_apart_from_the_accelerometer():
    """On wheels the accelerometer's test holds the constraint's channel: a constraint whose innovations
    run 3 times its model (sensors swinging ahead of an axle the filter does not know of) is said as
    such, and the accelerometer, which fits, is not blamed."""
    from guard.core.fit import ModelFit
    from guard.model.sensors import Sensor
    rng = np.random.default_rng(3)
    fit = ModelFit()
    for i in range(200 * 50):                       # 200 s at 50 Hz
        r = rng.normal(0.0, 1.0, 3) * [1.0, 1.0, 3.0]
        fit.add(Sensor.ACCEL, i * 20_000, r, np.eye(3))
    said = [n.text for n in fit.check(200 * 1_000_000)]
    assert len(said) == 1 and said[0].startswith("accel lateral innovations"), said
    assert 2.5 < fit.factor("accel lateral") <= 3.0 and fit.factor(Sensor.ACCEL) < 1.1   # (each z^2 clipped at 25)


def test_a_compass_slower_than_the_imu_has_its_noise_measured_between_its_own_readings():
    """A 10 Hz compass among 100 Hz IMU samples (as DataFlash and ULog logs give it: a reading on one
    IMU sample in ten) on a vehicle turning at 0.5 rad/s, 3 degrees of noise per reading: its noise
    is measured between consecutive readings, less what the gyro turned in between, its median over
    10 seeds within 10 % of the truth (compared sample to sample it was never measured: its test ran at
    the floor); a 1 Hz compass's too. A reading not yet measured is taken at NOISE_CAP times the floor,
    for START_CAP_S at most. And a 20 degree step
    written into one reading, after which the test is not calm, is not learnt by the slow memory:
    the compass's differences are learnt at the next reading, once the test has seen them."""
    from guard.core.aiding.imu import NOISE_CAP, ImuNoise
    floors = (0.15, 0.15, 0.01, 0.03)
    sigma = math.radians(3.0)
    read = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        noise = ImuNoise()
        for k in range(3000):
            t = T0_US + 10_000 * k
            theta = 0.5 * k / 100 + rng.normal(0.0, sigma) if k % 10 == 0 else None
            noise.add(t, 0.0, 0.0, 0.5 + rng.normal(0.0, 0.01), theta)
            if k == 25:                 # three readings: not measured yet
                assert noise.sigmas(floors, 1)[3] == NOISE_CAP * floors[3]
        read.append(math.sqrt(noise.var[3]))
    shown = [round(math.degrees(r), 2) for r in read]      # its memory holds 20 readings: each within 30 %
    assert abs(float(np.median(read)) / sigma - 1.0) < 0.1 and all(abs(r / sigma - 1.0) < 0.3 for r in read), shown
    # a 1 Hz compass: its readings a second apart are compared too, and one never measured would not
    # be held at the cap past START_CAP_S
    slow = ImuNoise()
    rng = np.random.default_rng(11)
    for k in range(12000):
        slow.add(T0_US + 10_000 * k, 0.0, 0.0, 0.5, 0.5 * k / 100 + rng.normal(0.0, sigma) if k % 100 == 0 else None)
    assert abs(math.sqrt(slow.var[3]) / sigma - 1.0) < 0.3 and slow.sigmas(floors, 1)[3] < NOISE_CAP * floors[3]
    twin = copy.deepcopy(noise)             # the same readings without the step
    for k in (3000, 3010, 3020):            # the step's reading (calm before it), then the test not calm
        for n, step in ((noise, math.radians(20.0)), (twin, 0.0)):
            n.add(T0_US + 10_000 * k, 0.0, 0.0, 0.5, 0.5 * k / 100 + (step if k == 3000 else 0.0), calm=k == 3000)
    assert noise.var[3] == twin.var[3]


@pytest.mark.parametrize("seed", [1, 2])
def test_a_noisy_compass_at_10_hz_is_quiet_from_its_first_reading_and_a_turn_still_caught(seed):
    """A 10 Hz compass with 4 degrees of noise per reading among 50 Hz IMU samples (a coarse
    magnetometer; real ones read 1 to 6 degrees between readings): quiet for 3 minutes, in the air and on
    wheels, from its first readings (tested at the floor before their noise was measured, it alarmed
    within half a second), and a 20 degree turn of it at 120 s is caught within a second."""
    base = drive(180.0, yaw=0.4, seed=seed)
    _, events = run(_slow_compass(base, 5, 4.0, seed), AIR)
    assert of(events, Alarm) == []
    k = next(i for i, s in enumerate(base) if s.t_us >= T0_US + 120_000_000)
    turned = drive(180.0, yaw=0.4, seed=seed, mag_offset_deg=20.0)
    _, events = run(_slow_compass(base[:k] + turned[k:], 5, 4.0, seed), GROUND)
    alarms = of(events, Alarm)
    assert alarms and alarms[0].sensor == "mag" and 0 <= alarms[0].t_us - (T0_US + 120_000_000) < 1_000_000, alarms[:1]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_stream_without_any_imu_is_tested_on_its_gnss_alone_and_does_not_diverge(seed):
    """GNSS alone, no IMU sample at all (a ground station's tlog of an autopilot that sends only its
    ATTITUDE), a fix every 1.6 s at 8 m/s: after NO_IMU_S the GNSS is tested alone, said once, the
    heading held. Run as if an IMU would come, the filter's unmeasured heading and yaw rate turned its
    velocity away and it diverged, re-initialised, every minute or so (and on one seed alarmed). A
    20 m step at 200 s (4.5 sigma of what 1.6 s of a vehicle's own manoeuvres allow) is caught at its
    fix; an IMU that speaks later is integrated, by a new filter."""
    from guard.core.monitor import NO_IMU_S
    samples = drive(300.0, yaw=0.4, seed=seed, speed=8.0,
                    gnss_offset=lambda t: (0.0, 20.0 if t >= 200.0 else 0.0))
    fixes = [s for s in samples if isinstance(s, GnssFix)][::8]
    mon, events = run(fixes, AIR)
    said = [n for n in of(events, Notice) if n.level == "warning" and n.t_us < T0_US + 200_000_000]
    assert [n.text.split(":")[0] for n in said] == [f"no IMU sample in {NO_IMU_S:g} s of GNSS"], said
    assert mon.inertial is False
    alarm, *_ = of(events, Alarm)
    assert alarm.sensor in ("gnss_pos", "gnss_vel") and 0 <= alarm.t_us - (T0_US + 200_000_000) <= 1_600_000, alarm
    quiet = [e for e in of(events, Estimate) if e.t_us < T0_US + 200_000_000]
    assert max(math.hypot(e.x[0] - 8.0 * math.cos(0.4) * (e.t_us - T0_US) / 1e6,
                          e.x[1] - 8.0 * math.sin(0.4) * (e.t_us - T0_US) / 1e6) for e in quiet) < 2.0
    k = len([s for s in samples if s.t_us < T0_US + 60_000_000])     # the IMU speaks from 60 s on
    late = [s for s in samples[:k] if isinstance(s, GnssFix)][::8] + samples[k:]
    mon, events = run(late, AIR)
    assert [n for n in of(events, Notice) if n.text.startswith("IMU at") and "after none: integrated" in n.text]
    # its first samples, before its rate was judged, are not said to be a slow stream's
    assert "imu_too_slow" not in mon.skipped and 0 < mon.skipped["imu_rate_unknown"] < 50, mon.skipped


