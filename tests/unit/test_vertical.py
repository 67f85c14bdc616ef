"""The accelerometers' vertical reading against the GNSS altitude (guard.core.aiding.vertical): quiet on
a vehicle that climbs and sinks with a receiver's altitude noise; a WARNING naming the accelerometers
where they stop reading the vehicle (a clipped or biased vertical axis), or the attitude where the
accelerometers read 1 g and the roll and pitch that level them are wrong; nothing for a receiver's
altitude jump; and, in the monitor, only on an IMU fast enough to integrate."""

import dataclasses
import math

import numpy as np
import pytest

from guard.core.aiding.vertical import G, VerticalCheck
from guard.model.events import Notice
from guard.model.samples import GnssFix, ImuSample
from unit.synthetic import T0_US, drive, of, run


def flight(seconds, seed, vib=0.5, alt_noise=0.3, imu_hz=50, gnss_hz=5, up_bias=None, roll_off=None,
           alt_jump=None):
    """(t_us, kind, values) of a vehicle climbing and sinking (vertical acceleration 1.5 sin(0.3 t)
    m/s^2), level: its IMU's specific force with vibration, its fixes' altitude with white noise.
    up_bias(t): added to the IMU's upward reading (-f_z); roll_off(t): the roll it is levelled with
    (rad), its accelerometers level; alt_jump(t): added to the fixes' altitude."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(int(seconds * imu_hz)):
        t = i / imu_hz
        a_up = 1.5 * math.sin(0.3 * t)
        f_z = -(G + a_up) - (up_bias(t) if up_bias else 0.0)
        acc = rng.normal(0.0, vib, 3) + (0.0, 0.0, f_z)
        s = ImuSample(T0_US + round(t * 1e6), *acc, 0.0, 0.0, 0.0, None, None, None)
        out.append((s.t_us, "imu", (s, roll_off(t) if roll_off else 0.0, 0.0)))
    for j in range(int(seconds * gnss_hz)):
        t = j / gnss_hz
        alt = 100.0 + 1.5 / 0.09 * (0.3 * t - math.sin(0.3 * t)) + rng.normal(0.0, alt_noise)
        out.append((T0_US + round(t * 1e6), "gnss", alt + (alt_jump(t) if alt_jump else 0.0)))
    return sorted(out, key=lambda r: (r[0], r[1] == "imu"))


def said(rows):
    v, notes = VerticalCheck(), []
    for t_us, kind, x in rows:
        notes += v.imu(*x) if kind == "imu" else v.fix(t_us, x)
    return notes


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("vib, alt_noise, imu_hz, gnss_hz", [(0.5, 0.3, 50, 5), (3.0, 0.8, 25, 5),
                                                              (1.0, 0.5, 10, 1)])
def test_a_vehicle_that_climbs_and_sinks_is_quiet(seed, vib, alt_noise, imu_hz, gnss_hz):
    assert said(flight(180.0, seed, vib, alt_noise, imu_hz, gnss_hz)) == []


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("bias", [-6.0, 5.0])
def test_accelerometers_that_stop_reading_the_vehicle_are_named_once(seed, bias):
    """From 60 s to 120 s the vertical axis reads `bias` m/s^2 off (a clipped accelerometer, or an
    injection): said within 10 s, once for the episode, as the accelerometers' fault."""
    notes = said(flight(180.0, seed, up_bias=lambda t: bias if 60.0 <= t < 120.0 else 0.0))
    assert len(notes) == 1, [n.text for n in notes]
    n = notes[0]
    assert T0_US + 60e6 < n.t_us <= T0_US + 70e6 and n.level == "warning"
    assert n.text.startswith("the accelerometers read the vehicle accelerating") and "clipping" in n.text, n.text
    reads = float(n.text.split("accelerating ")[1].split(" m/s^2")[0])
    assert abs(reads - bias) < 2.0, n.text


def test_a_second_episode_after_a_quiet_spell_is_said_again():
    bias = lambda t: 6.0 if 30.0 <= t < 50.0 or 120.0 <= t < 140.0 else 0.0     # noqa: E731
    notes = said(flight(180.0, 4, up_bias=bias))
    assert [round((n.t_us - T0_US) / 1e6) // 10 for n in notes] == [3, 12], [n.t_us for n in notes]


@pytest.mark.parametrize("seed", [1, 2])
def test_an_attitude_that_does_not_level_the_imu_is_named(seed):
    """The accelerometers read 1 g and the roll they are levelled with is 50 degrees off from 60 s
    (a diverged attitude, a log's wrong field): said as the attitude's fault, not theirs."""
    notes = said(flight(120.0, seed, roll_off=lambda t: math.radians(50.0) if t >= 60.0 else 0.0))
    assert len(notes) == 1 and "the attitude is wrong" in notes[0].text, [n.text for n in notes]
    assert T0_US + 60e6 < notes[0].t_us <= T0_US + 70e6


def test_a_receivers_altitude_jump_is_not_the_imus():
    """The fixes' altitude jumps 30 m for 5 s, then back: the GNSS's own vertical acceleration is far
    past what a vehicle holding its climb shows, so nothing is said of the IMU."""
    notes = said(flight(120.0, 5, alt_jump=lambda t: 30.0 if 60.0 <= t < 65.0 else 0.0))
    assert notes == [], [n.text for n in notes]


def test_the_monitor_says_it_of_a_fast_imu_and_not_of_telemetrys():
    """The core's drive with its accelerometers' z reading 6 m/s^2 less from 30 s: said once at 50 Hz;
    at 1 Hz (telemetry's RAW_IMU, GNSS alone) nothing is said: such an IMU samples its vibration."""
    samples = drive(90.0, seed=6)
    off = [dataclasses.replace(s, acc_z_mps2=s.acc_z_mps2 + 6.0) if isinstance(s, ImuSample) and
           s.t_us >= T0_US + 30e6 else s for s in samples]
    texts = [n.text for n in of(run(off)[1], Notice) if "upward over 4 s" in n.text]
    assert len(texts) == 1 and texts[0].startswith("the accelerometers read"), texts
    assert not [n for n in of(run(samples)[1], Notice) if "upward over 4 s" in n.text]
    slow = [s for s in off if isinstance(s, GnssFix) or (s.t_us - T0_US) % 1_000_000 == 0]
    mon, events = run(slow)
    assert mon.inertial is False and not [n for n in of(events, Notice) if "upward over 4 s" in n.text]
