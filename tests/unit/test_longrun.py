"""The long-run scale of a test (guard.core.longrun): 1 for white innovations, the wander's factor
for correlated ones, bounded, said once; and on a vehicle whose compass wanders, the alarms it
would raise gone while a compass attack is still caught."""

import dataclasses
import math

import numpy as np
import pytest

from guard.core.longrun import BLOCK, F_MAX, LongRun
from guard.core.monitor import MonitorConfig
from guard.model.events import Alarm, Notice
from guard.model.samples import ImuSample
from guard.model.sensors import Sensor
from unit.synthetic import T0_US, drive, of, run

S1 = np.eye(1)


def feed(lr, z, dt_us=20_000):
    said = []
    for i, zi in enumerate(z):
        n = lr.add(Sensor.MAG, T0_US + i * dt_us, np.array([zi]), S1)
        if n:
            said.append(n)
    return said


def ar1(n, rho, sd, seed):
    rng = np.random.default_rng(seed)
    e = rng.normal(0.0, sd * math.sqrt(1.0 - rho * rho), n)
    z = np.empty(n)
    z[0] = rng.normal(0.0, sd)
    for i in range(1, n):
        z[i] = rho * z[i - 1] + e[i]
    return z


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_white_innovations_leave_the_test_as_it_is(seed):
    lr = LongRun()
    said = feed(lr, np.random.default_rng(seed).normal(0.0, 1.0, 400 * BLOCK))
    assert lr.factors(Sensor.MAG)[0] < 1.25 and said == []


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_model_too_generous_per_sample_is_never_made_more_sensitive(seed):
    lr = LongRun()
    feed(lr, np.random.default_rng(seed).normal(0.0, 0.3, 200 * BLOCK))
    assert lr.factors(Sensor.MAG)[0] == 1.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_correlated_innovations_widen_the_test_by_their_long_run_factor_and_it_is_said_once(seed):
    """AR(1), rho 0.9, 0.5 per sample: the long-run standard deviation is 0.5 sqrt(19) = 2.2 (less the
    part of the correlation longer than a block, which the block means do not see)."""
    lr = LongRun()
    said = feed(lr, ar1(400 * BLOCK, 0.9, 0.5, seed))
    f = lr.factors(Sensor.MAG)[0]
    assert 1.6 < f < 2.4, f
    assert len(said) == 1 and said[0].level == "warning" and "mag innovations wander" in said[0].text


def test_the_scale_is_bounded():
    lr = LongRun()
    feed(lr, ar1(200 * BLOCK, 0.999, 3.0, 4))
    assert lr.factors(Sensor.MAG)[0] == F_MAX


def _wandering_compass(samples, deg, tau_s, seed, step_deg=0.0, step_s=math.inf):
    """The compass turned by a wander of `deg` (1 sigma) correlated over tau_s, as a compass on a
    real vehicle reads (a multicopter's motor field and tilt, a car's electrics); from step_s on,
    step_deg more (an attack)."""
    rng = np.random.default_rng(seed)
    a, out = 0.0, []
    rho = math.exp(-0.02 / tau_s)                   # the IMU's 50 Hz
    for s in samples:
        if isinstance(s, ImuSample) and s.mag_x_gauss is not None:
            a = rho * a + math.sqrt(1.0 - rho * rho) * rng.normal(0.0, math.radians(deg))
            turn = a + (math.radians(step_deg) if s.t_us >= T0_US + step_s * 1e6 else 0.0)
            c, sn = math.cos(turn), math.sin(turn)
            s = dataclasses.replace(s, mag_x_gauss=c * s.mag_x_gauss - sn * s.mag_y_gauss,
                                    mag_y_gauss=sn * s.mag_x_gauss + c * s.mag_y_gauss)
        out.append(s)
    return out


GROUND = MonitorConfig(declination_deg=0.0, vehicle="ground")
WIDENED = dataclasses.replace(GROUND, max_wander_factor=4.0)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_wandering_compass_alarms_as_the_model_says_and_not_widened_and_an_attack_is_still_caught(seed, runs):
    """A compass that wanders by 2 degrees over 3 s on a ground vehicle: tested as the model says
    (the default), its wander raises alarms every half minute or so; widened (max_wander_factor 4),
    the wander is said and after the first minute, once the factor is learnt, at most half as many
    come (over seeds 1 to 10: 6 to 14 after the first minute with the default, 0 to 4 widened; the
    test said "none after the first minute" until a start's first samples were taken at the noise
    cap, which moves which alarms come when: on the code before, 4 of those 10 seeds had some too);
    a 15 degree turn of the compass at 240 s is still caught within 1.5 s."""
    samples = _wandering_compass(drive(300.0, yaw=0.4, seed=seed), 2.0, 3.0, seed)
    _, events = run(samples, GROUND)
    assert len([a for a in of(events, Alarm) if a.sensor == Sensor.MAG]) >= 5
    late = [a for a in of(events, Alarm) if a.t_us >= T0_US + 60_000_000]
    mon, events = runs.run(samples, WIDENED, at_us=(T0_US + 240_000_000,))   # the attacked run below: once
    alarms = of(events, Alarm)
    assert len([a for a in alarms if a.t_us >= T0_US + 60_000_000]) <= len(late) / 2, (alarms, len(late))
    assert any(n.text.startswith("mag innovations wander") for n in of(events, Notice))
    assert mon.longrun.factors(Sensor.MAG)[0] > 1.5
    attacked = _wandering_compass(drive(300.0, yaw=0.4, seed=seed), 2.0, 3.0, seed, 15.0, 240.0)
    _, events = runs.run(attacked, WIDENED)
    after = [a for a in of(events, Alarm) if a.t_us >= T0_US + 240_000_000]
    assert after and after[0].sensor == Sensor.MAG and after[0].t_us - (T0_US + 240_000_000) < 1_500_000, after[:1]


def test_off_by_default():
    assert MonitorConfig().max_wander_factor == 1.0


def test_a_sensor_that_gains_a_channel_starts_its_wander_again():
    """The accelerometer gains its "lateral" channel when the vehicle is found on wheels: the wander
    learnt on two channels is not applied to three, and is learnt afresh."""
    lr = LongRun()
    for i, z in enumerate(ar1(200 * BLOCK, 0.9, 0.5, 4)):
        lr.add(Sensor.ACCEL, T0_US + i * 20_000, np.array([z, z]), np.eye(2))
    assert lr.factors(Sensor.ACCEL).max() > 1.5
    assert np.array_equal(lr.scale(Sensor.ACCEL, np.eye(3)), np.eye(3))
    t0 = T0_US + 200 * BLOCK * 20_000
    for i, z in enumerate(np.random.default_rng(4).normal(0.0, 1.0, 2 * BLOCK)):
        lr.add(Sensor.ACCEL, t0 + i * 20_000, np.array([z, z, z]), np.eye(3))
    assert lr.factors(Sensor.ACCEL).shape == (3,)
