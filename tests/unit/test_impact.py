"""A blow at the IMU (guard.core.aiding.impact): a point-sampled impact is set aside, not integrated
into a velocity that never happened; an attack after it, or one dressed as a string of blows, is caught."""

import dataclasses
import math

import numpy as np
import pytest

from guard.core.aiding import impact
from guard.core.ekf import VX, FilterConfig, NavEKF
from guard.core.history import History
from guard.model.events import Alarm, Notice
from guard.model.samples import ImuSample
from unit.synthetic import T0_US, drive, of, run

BLOW_AT_S = 60.0
# three samples (60 ms at 50 Hz) of a blow as an IMU logged at 50 Hz reads it: 4 to 6 g, one way,
# while the vehicle (its GNSS) goes on as it was
BLOW = ((38.0, -22.0, -50.0), (-30.0, 18.0, -60.0), (12.0, 25.0, -35.0))


def blown(samples, at_s=BLOW_AT_S, blow=BLOW):
    out, k = [], None
    for s in samples:
        if isinstance(s, ImuSample) and s.t_us >= T0_US + at_s * 1e6 and (k is None or k < len(blow)):
            k = 0 if k is None else k
            s = dataclasses.replace(s, acc_x_mps2=blow[k][0], acc_y_mps2=blow[k][1], acc_z_mps2=blow[k][2])
            k += 1
        out.append(s)
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_blow_is_set_aside_and_raises_nothing(seed, runs):
    # the tests below go on from the blow's time or a second after it
    mon, events = runs.run(blown(drive(120.0, yaw=0.7, seed=seed)), at_us=(T0_US + BLOW_AT_S * 1e6,
                                                                          T0_US + (BLOW_AT_S + 1.0) * 1e6))
    assert of(events, Alarm) == []
    said = [n for n in of(events, Notice) if "blow at the IMU" in n.text]
    first_g = math.dist(BLOW[0], (0.0, 0.0, 0.0)) / impact.G
    assert len(said) == 1 and f"{first_g:.1f} g" in said[0].text, said
    assert len(BLOW) + 24 <= mon.skipped["imu_impact"] <= len(BLOW) + 26    # and 0.5 s at 50 Hz after it


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_same_blow_integrated_alarms(seed, monkeypatch):
    """The control: with the rule off, the same blow, integrated as if it lasted each sample's 20 ms,
    is an alarm."""
    monkeypatch.setattr(impact, "IMPACT_G", 1e9)
    mon, events = run(blown(drive(120.0, yaw=0.7, seed=seed)))
    assert of(events, Alarm)
    assert "imu_impact" not in mon.skipped


def _first_alarm_after(runs, samples, start):
    alarms = [a for a in of(runs.run(samples)[1], Alarm) if a.t_us >= start]
    return (alarms[0].t_us - start) / 1e6 if alarms else None


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_accelerometer_attack_just_after_a_blow_is_caught_as_without_it(seed, runs):
    """0.5 m/s^2 on x from 1 s after the blow (within 0.5 s of the IMU's return): caught as soon as the
    same attack on the same drive without a blow."""
    start = T0_US + (BLOW_AT_S + 1.0) * 1e6

    def attacked(samples):
        return [dataclasses.replace(s, acc_x_mps2=s.acc_x_mps2 + 0.5) if isinstance(s, ImuSample) and
                s.t_us >= start else s for s in samples]
    clean = drive(120.0, yaw=0.7, seed=seed)
    without = _first_alarm_after(runs, attacked(clean), start)
    after = _first_alarm_after(runs, attacked(blown(clean)), start)
    assert without is not None and after is not None and after <= without + 0.5, (without, after)


def test_blows_that_do_not_stop_are_not_blows(runs):
    """An attacker writing 4 g into every fourth accelerometer sample from 60 s: the IMU is set aside
    at most BUDGET_S of WINDOW_S, then used and tested as it reads, with a warning, and the attack is caught."""
    start = T0_US + BLOW_AT_S * 1e6
    samples = [dataclasses.replace(s, acc_x_mps2=40.0) if isinstance(s, ImuSample) and s.t_us >= start
               and (s.t_us - T0_US) // 20_000 % 4 == 0 else s for s in drive(120.0, yaw=0.7, seed=1)]
    mon, events = runs.run(samples)
    warned = [n for n in of(events, Notice) if "not blows" in n.text]
    assert len(warned) == 1 and warned[0].t_us - start <= (impact.BUDGET_S + 0.1) * 1e6, warned
    alarms = of(events, Alarm)
    assert alarms and 0 <= alarms[0].t_us - warned[0].t_us < 1e6, alarms[:1]


def test_a_rewind_over_a_blow_adds_it_again():
    """A GNSS alarm's rewind re-runs the IMU fusions since the attack's first epoch: a blow among them
    widens the velocity again, as it did the first time."""
    def rewound(with_blow):
        ekf = NavEKF(FilterConfig(), np.zeros(13))
        h = History(20.0, 0.0, 50.0)
        h.epoch(0, ekf.x, ekf.P)
        if with_blow:
            h.blow(100_000, 4.0)
        h.rewind(ekf, 1, 200_000)
        return ekf.P[VX, VX]
    assert rewound(True) - rewound(False) == pytest.approx(4.0, rel=0.01)


def test_the_budget_is_a_window_not_a_switch(runs):
    """A string of blows from 60 to 63 s spends the budget (the warning); a real blow 90 s later is
    set aside again, as the first would have been, and raises nothing."""
    start, stop = T0_US + 60e6, T0_US + 63e6
    samples = [dataclasses.replace(s, acc_x_mps2=40.0) if isinstance(s, ImuSample) and start <= s.t_us < stop
               and (s.t_us - T0_US) // 20_000 % 4 == 0 else s for s in drive(200.0, yaw=0.7, seed=1)]
    mon, events = runs.run(blown(samples, at_s=150.0))
    assert [n for n in of(events, Notice) if "not blows" in n.text]
    later = [a for a in of(events, Alarm) if a.t_us >= T0_US + 149e6]
    assert later == [], later[:1]
    assert impact.HOLD_S * 50 <= mon.skipped["imu_impact"], mon.skipped


def fast_imu(samples, hz=220):
    """The drive's IMU on one continuous `hz` clock (each sample's reading that of the latest 50 Hz
    sample), GNSS as it was."""
    out, step, t = [], 1e6 / hz, None
    for s, nxt in zip(samples, samples[1:] + [None]):
        if not isinstance(s, ImuSample):
            out.append(s)
            continue
        t = s.t_us if t is None else t
        end = nxt.t_us if nxt is not None else s.t_us + 20_000
        while t < end:
            out.append(dataclasses.replace(s, t_us=int(round(t))))
            t += step
    return out


def test_vibration_has_no_mean_and_is_no_blow():
    """A badly damped IMU at 220 Hz shaken at 80 Hz, 5 g on x (no mean): nothing set aside; the same
    IMU with a blow of 5 g over 14 ms (3 samples) has it set aside."""
    def shaken(samples):
        return [dataclasses.replace(s, acc_x_mps2=s.acc_x_mps2 + 49.0 * math.sin(2 * math.pi * 80.0 * s.t_us / 1e6))
                if isinstance(s, ImuSample) else s for s in samples]
    vib = shaken(fast_imu(drive(40.0, yaw=0.7, seed=1)))
    mon, _ = run(vib)
    assert "imu_impact" not in mon.skipped, mon.skipped
    mon, events = run(blown(fast_imu(drive(40.0, yaw=0.7, seed=1)), at_s=30.0))
    assert mon.skipped["imu_impact"] > 0 and [n for n in of(events, Notice) if "blow at the IMU" in n.text]
