"""The motors' start heard in the IMU, and the compass's offset their current makes learnt, not alarmed
(guard.core.aiding.motors)."""

import math

import numpy as np
import pytest

from guard.core.aiding import motors
from guard.core.aiding.imu import ImuNoise
from guard.core.aiding.motors import OPEN_S, STOP_S, MotorWatch
from guard.core.ekf import BM
from guard.core.monitor import MonitorConfig
from guard.model.events import Alarm, Estimate, Notice
from unit.synthetic import T0_US, drive, of, run

AIR = MonitorConfig(declination_deg=0.0, vehicle="air")
GROUND = MonitorConfig(declination_deg=0.0, vehicle="ground")
START_S = 30.0      # the motors start; the vehicle lifts off a second later


def take_off(turn_deg: float, over_s: float = 3.0, then=None):
    """The compass as the motors' current turns it: nothing before lift-off, then turn_deg laid in over
    over_s; `then(t)` adds a further turn (an attack)."""
    def turn(t):
        lift = START_S + 1.0
        own = 0.0 if t < lift else turn_deg * min(1.0, (t - lift) / over_s)
        return own + (then(t) if then else 0.0)
    return turn


def flight(seed, turn_deg, duration_s=90.0, then=None):
    return drive(duration_s, yaw=0.4, seed=seed, vibration=lambda t: 1.0 if t >= START_S else 0.0,
                 mag_turn=take_off(turn_deg, then=then))


@pytest.mark.parametrize("vehicle", [AIR, GROUND], ids=["air", "ground"])
@pytest.mark.parametrize("seed,turn_deg", [(1, 20.0), (2, -15.0), (3, 35.0)])
def test_the_compass_turned_by_the_motors_current_is_learnt_not_alarmed(vehicle, seed, turn_deg, runs):
    """The motors start at 30 s (the accelerometers' noise from 0.03 to 1 m/s^2) and, from lift-off a
    second later, their current turns the compass by 15 to 35 degrees over 3 s (the real flights of the
    README: 5 to 39 degrees). Heard, said once, learnt as the compass's offset: no alarm, and by the
    window's end the heading within 1 degree of the true one on wheels (the sideways constraint holds
    it), within 5 in the air (the gyro alone holds it while the compass's offset moves: on a straight
    line nothing else observes it), the offset the rest of the compass's turn; and the turn is said
    when the window closes."""
    # the flights below go on from lift-off, or from a compass's jump
    mon, events = runs.run(flight(seed, turn_deg), vehicle,
                           at_us=[T0_US + t * 1e6 for t in (START_S + 1.0, 33.0, START_S + OPEN_S + 10.0)])
    assert of(events, Alarm) == []
    said = [(round((e.t_us - T0_US) / 1e6, 1), e.text) for e in of(events, Notice) if "the motors" in e.text[:12]]
    assert len(said) == 1 and START_S <= said[0][0] <= START_S + 0.5 and "started" in said[0][1], said
    end = next(e for e in of(events, Estimate) if e.t_us >= T0_US + (START_S + OPEN_S) * 1e6)
    error = math.degrees(math.remainder(end.yaw_rad - 0.4, math.tau))
    assert abs(error) < (1.0 if vehicle is GROUND else 5.0), error
    assert abs(math.degrees(end.x[BM]) + turn_deg + error) < 1.0, (math.degrees(end.x[BM]), error)
    # and how far it turned is said when the window closes, a WARNING from 10 degrees
    turned = [e for e in of(events, Notice) if "the compass turned" in e.text]
    assert len(turned) == 1 and turned[0].level == "warning" and "compassmot" in turned[0].text, turned
    assert abs(turned[0].t_us - (T0_US + (START_S + OPEN_S) * 1e6)) <= 500_000, turned
    said_deg = float(turned[0].text.split("turned ")[1].split(" deg")[0])
    assert abs(said_deg - turn_deg) < (1.0 if vehicle is GROUND else 6.0), turned[0].text


@pytest.mark.parametrize("vehicle", [AIR, GROUND], ids=["air", "ground"])
def test_a_turn_beyond_what_a_current_makes_is_said_as_such(vehicle, runs):
    """A compass turned 70 degrees over 3 s at lift-off (the real flights' currents: 5 to 39): the
    window learns it as it would a current's (the cost the module's docstring states), but what is
    said when it closes is that it is more than a current makes, not a compassmot hint."""
    mon, events = runs.run(flight(1, 70.0), vehicle)
    turned = [e for e in of(events, Notice) if "the compass turned" in e.text]
    assert len(turned) == 1 and turned[0].level == "warning", turned
    assert "more than a motors' current" in turned[0].text and "compassmot" not in turned[0].text, turned[0].text
    assert abs(float(turned[0].text.split("turned ")[1].split(" deg")[0]) - 70.0) < 6.0, turned[0].text


@pytest.mark.parametrize("seed,still_deg", [(1, 0.0), (2, 3.0), (3, -4.0)])
def test_the_offset_with_the_motors_still_is_what_tune_writes(seed, still_deg):
    """A car whose compass is still_deg off at rest and turned 20 degrees more by its motors: the
    filter's b_psi ends at the sum, and the offset with the motors still (what `guard tune` writes, as
    every flight learns its take-off anew) at still_deg alone, within 1 degree."""
    samples = drive(90.0, yaw=0.4, seed=seed, vibration=lambda t: 1.0 if t >= START_S else 0.0,
                    mag_offset_deg=still_deg, mag_turn=take_off(20.0))
    mon, events = run(samples, GROUND)
    assert abs(math.degrees(mon.ekf.x[BM]) + still_deg + 20.0) < 1.0, math.degrees(mon.ekf.x[BM])
    assert abs(math.degrees(mon.motors.still_offset(mon.ekf)) + still_deg) < 1.0


@pytest.mark.parametrize("seed,turn_deg", [(1, 20.0), (2, -15.0), (3, 35.0)])
def test_without_the_window_the_same_take_off_alarms_the_compass(seed, turn_deg, monkeypatch):
    """The control: the offset's random walk left as configured through the motors' start, the same
    flights raise a magnetometer alarm within 10 s of lift-off."""
    monkeypatch.setattr(motors, "Q_OPEN", 0.0)
    mon, events = run(flight(seed, turn_deg), AIR)
    alarms = of(events, Alarm)
    assert alarms and alarms[0].sensor == "mag", alarms[:1]
    assert 0 <= alarms[0].t_us - (T0_US + (START_S + 1.0) * 1e6) <= 10_000_000, alarms[:1]


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("at_s,jump_deg", [(33.0, 40.0), (START_S + OPEN_S + 10.0, 12.0)],
                         ids=["in-the-window", "after-it"])
def test_a_compass_that_jumps_is_still_caught_in_the_window_and_after(seed, at_s, jump_deg, runs):
    """An attack on the magnetometer, in one reading: 40 degrees 3 s after the motors' start (the
    window open: a fast change is no current's) or 12 degrees 10 s after the window closed (the
    compass's test as tight as before the motors): caught within 1 s either way."""
    samples = flight(seed, 20.0, then=lambda t: jump_deg if t >= at_s else 0.0)
    mon, events = runs.run(samples, AIR, at_us=(T0_US + 33e6,))
    alarms = of(events, Alarm)
    assert alarms and alarms[0].sensor == "mag", alarms[:1]
    assert 0 <= alarms[0].t_us - (T0_US + at_s * 1e6) <= 1_000_000, alarms[:1]


def _levels(noise_at, seconds, seed, hz=50):
    """The vibration level ImuNoise gives per sample of an accelerometer whose noise is noise_at(t)."""
    rng = np.random.default_rng(seed)
    noise, out = ImuNoise(), []
    for k in range(int(seconds * hz)):
        t = k / hz
        a = rng.normal(0.0, noise_at(t), 2)
        noise.add(T0_US + int(k * 1e6 / hz), a[0], a[1], 0.0, None)
        out.append((T0_US + int(k * 1e6 / hz), noise.vibration()))
    return out


def _said(levels):
    watch = MotorWatch()
    return [(round((t - T0_US) / 1e6, 2), w) for t, level in levels if (w := watch.add(t, level))]


@pytest.mark.parametrize("seed", range(5))
def test_the_motors_are_heard_starting_and_stopping_and_a_still_imu_never_starts_them(seed):
    """A still IMU (0.03 to 0.05 m/s^2 of noise, 10 minutes at 50 Hz) never starts its motors; motors
    of 0.5 m/s^2 from 20 s to 80 s are heard starting within 0.5 s and stopping within STOP_S + 1 s
    (the level smoothed); an IMU that vibrates from its first sample (a log begun in flight) has no
    start, but its stop, to 0.03 m/s^2 and to a noisy still IMU's 0.06 (with no still level heard,
    the stop's line is the running level over RISE, between VIB_FLOOR / 2 and VIB_FLOOR), and a
    flight whose vibration swings with the throttle between 0.25 and 0.6 m/s^2 never stops."""
    still = 0.03 + 0.02 * seed / 4
    assert _said(_levels(lambda t: still, 600.0, seed)) == []
    said = _said(_levels(lambda t: 0.5 if 20.0 <= t < 80.0 else still, 120.0, seed))
    assert [w for _, w in said] == ["start", "stop"], said
    assert 20.0 <= said[0][0] <= 20.5 and 80.0 + STOP_S <= said[1][0] <= 80.0 + STOP_S + 1.0, said
    for landed in (0.03, 0.06):
        said = _said(_levels(lambda t: 0.5 if t < 30.0 else landed, 60.0, seed))
        assert [w for _, w in said] == ["stop"] and 30.0 + STOP_S <= said[0][0] <= 30.0 + STOP_S + 1.0, (landed, said)
    assert _said(_levels(lambda t: 0.425 + 0.175 * math.sin(t / 3.0), 300.0, seed)) == []


@pytest.mark.parametrize("seed", [1, 2])
def test_an_imu_too_slow_to_integrate_is_not_listened_to_for_the_motors(seed):
    """Telemetry's RAW_IMU at 2 Hz (the IMU not integrated, the GNSS tested alone), whose vibration comes
    and goes every 10 s: no motors' start or stop is said (at that rate the second differences are the
    vehicle's manoeuvres, and the watch said one every few seconds on a real telemetry log, of a
    compass window no test used). The same vibration at 50 Hz is heard."""
    vib = lambda t: 1.0 if int(t // 10) % 2 else 0.0     # noqa: E731
    samples = drive(90.0, yaw=0.4, seed=seed, vibration=vib)
    slow, k = [], 0
    for s in samples:
        if hasattr(s, "acc_x_mps2"):
            k += 1
            if k % 25:
                continue
        slow.append(s)
    mon, events = run(slow, AIR)
    assert mon.inertial is False and not [n for n in of(events, Notice) if "motors" in n.text]
    _, events = run(samples, AIR)
    assert [n for n in of(events, Notice) if "the motors started" in n.text]
