"""The accelerometers at rest (guard.core.aiding.rest): quiet on calibrated IMUs at rest over noise
profiles and rates, tilted or not; a WARNING with the figure where they read gravity more than 0.75
m/s^2 off, once per episode; nothing while the vehicle moves, turns or vibrates; and, in the monitor, at
an IMU's full rate as at telemetry's 1 Hz."""

import dataclasses
import math

import numpy as np
import pytest

from guard.core.aiding.rest import G, RestCheck
from guard.model.events import Notice
from guard.model.samples import GnssFix, ImuSample
from unit.synthetic import T0_US, drive, of, run


def standing(seconds, seed, imu_hz=50, vib=0.05, tilt_deg=0.0, scale=lambda t: 1.0, offset=(0.0, 0.0, 0.0),
             speed=0.0, gyro=0.0, accel=0.0, gnss_hz=5):
    """(t_us, kind, sample) of a vehicle standing on a slope of tilt_deg (its roll), its accelerometers
    reading gravity times scale(t) plus offset (body axes) plus white noise of vib; accel: a forward
    acceleration it reads besides (m/s^2); gyro: a yaw rate (rad/s); fixes at gnss_hz with the
    horizontal speed `speed` (None: no fixes)."""
    rng = np.random.default_rng(seed)
    r = math.radians(tilt_deg)
    out = []
    for i in range(int(seconds * imu_hz)):
        t = i / imu_hz
        f = np.array([accel, -G * math.sin(r), -G * math.cos(r)]) * scale(t) + offset + rng.normal(0.0, vib, 3)
        w = rng.normal(0.0, 0.002, 3) + (0.0, 0.0, gyro)
        out.append((T0_US + round(t * 1e6), "imu", ImuSample(T0_US + round(t * 1e6), *f, *w, None, None, None)))
    if speed is not None:
        for j in range(int(seconds * gnss_hz)):
            out.append((T0_US + round(j / gnss_hz * 1e6), "gnss", speed))
    return sorted(out, key=lambda x: (x[0], x[1] == "imu"))


def judged(rows) -> tuple[list[Notice], RestCheck]:
    check, notes = RestCheck(), []
    for t_us, kind, x in rows:
        if kind == "imu":
            notes += check.imu(x)
        else:
            check.fix(t_us, x)
    return notes, check


def said(rows) -> list[Notice]:
    return judged(rows)[0]


def figure(note):
    return float(note.text.split("read ")[1].split(" m/s^2")[0])


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("imu_hz, vib, tilt_deg, offset, speed", [
    (50, 0.05, 0.0, (0.0, 0.0, 0.0), 0.0),
    (400, 0.3, 10.0, (0.3, -0.2, 0.5), 0.1),        # an idling motor, a slope, offsets within tolerance
    (10, 0.45, 25.0, (0.0, 0.0, -0.4), None),       # no fixes heard at all
    (1, 0.02, 5.0, (0.0, 0.0, 0.4), 0.0),           # telemetry's RAW_IMU
])
def test_calibrated_accelerometers_at_rest_are_quiet(seed, imu_hz, vib, tilt_deg, offset, speed):
    notes, check = judged(standing(120.0, seed, imu_hz, vib, tilt_deg, offset=offset, speed=speed))
    assert notes == [] and check.judged >= 15, (notes, check.judged)     # judged at rest, and found within
    assert abs(check.summary()["median_mps2"] - G) < 0.75


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("imu_hz, k", [(50, 0.84), (10, 1.1), (1, 0.9)])
def test_accelerometers_that_misread_gravity_are_said_once_with_the_figure(seed, imu_hz, k):
    notes = said(standing(120.0, seed, imu_hz, vib=0.1, tilt_deg=8.0, scale=lambda t: k))
    assert len(notes) == 1 and notes[0].level == "warning", [n.text for n in notes]
    assert notes[0].t_us <= T0_US + 16e6
    # within 3 sigma of a window's mean
    assert abs(figure(notes[0]) - k * G) < 0.01 + 3 * 0.1 / math.sqrt(5 * imu_hz), notes[0].text
    assert "calibrate the accelerometers" in notes[0].text and "injected" in notes[0].text


def test_an_offset_along_gravity_is_said_and_one_across_it_is_second_order():
    """An offset of 1 m/s^2 on the axis gravity lies along changes the length by 1; across it, by
    sqrt(g^2 + 1) - g = 0.05: at rest only the first can be seen."""
    assert len(said(standing(60.0, 4, offset=(0.0, 0.0, -1.0)))) == 1
    assert said(standing(60.0, 4, offset=(1.0, 0.0, 0.0))) == []


@pytest.mark.parametrize("how", ["moving", "turning", "vibrating", "manoeuvring"])
def test_a_vehicle_not_at_rest_is_not_judged(how):
    """Accelerometers 12 % off, on a vehicle that moves (GNSS 2 m/s), turns (0.2 rad/s), vibrates (1
    m/s^2) or accelerates more and more (the halves of a window disagree): not at rest, not judged."""
    k = lambda t: 1.12                                                      # noqa: E731
    rows = {"moving": standing(60.0, 5, scale=k, speed=2.0),
            "turning": standing(60.0, 5, scale=k, gyro=0.2),
            "vibrating": standing(60.0, 5, scale=k, vib=1.0)}.get(how)
    if rows is None:                # forward, growing from 0 to 1 m/s^2 over each 5 s: quiet, but not steady
        rows = [(t, kind, dataclasses.replace(x, acc_x_mps2=x.acc_x_mps2 + (t - T0_US) % 5_000_000 / 5e6)
                 if kind == "imu" else x) for t, kind, x in standing(60.0, 5, scale=k)]
    notes, check = judged(rows)
    assert notes == [] and check.judged == 0, check.summary()


def test_a_second_episode_after_a_window_within_tolerance_is_said_again():
    k = lambda t: 0.85 if t < 30.0 or t >= 60.0 else 1.0                     # noqa: E731
    notes = said(standing(100.0, 6, scale=k))
    assert [round((n.t_us - T0_US) / 1e6) for n in notes] == [10, 70], [n.t_us for n in notes]


def test_a_silence_starts_the_window_again():
    """Two windows' worth of samples, but a 3 s silence in the second: the window before it is dropped,
    and it takes two full windows after it to say anything."""
    rows = [r for r in standing(30.0, 7, scale=lambda t: 0.85) if not (7e6 <= r[0] - T0_US < 10e6)]
    notes = said(rows)
    assert len(notes) == 1 and notes[0].t_us >= T0_US + 20e6, [n.t_us for n in notes]


def test_the_monitor_says_it_at_an_imus_full_rate_and_at_telemetrys():
    """The core's drive, standing (speed 0), its accelerometers reading 15 % low: said once at 50 Hz, and
    at 1 Hz (telemetry's RAW_IMU: guard on GNSS alone, this check still run); not of the same IMU
    calibrated, nor of one 15 % low on a vehicle driving (at 5 m/s it is not at rest)."""
    def low(samples):
        return [dataclasses.replace(s, acc_x_mps2=0.85 * s.acc_x_mps2, acc_y_mps2=0.85 * s.acc_y_mps2,
                                    acc_z_mps2=0.85 * s.acc_z_mps2) if isinstance(s, ImuSample) else s
                for s in samples]

    def texts(samples):
        return [n.text for n in of(run(samples)[1], Notice) if "at rest over" in n.text]

    still = drive(60.0, speed=0.0, seed=8)
    assert len(texts(low(still))) == 1 and not texts(still)
    slow = [s for s in low(still) if isinstance(s, GnssFix) or (s.t_us - T0_US) % 1_000_000 == 0]
    mon, events = run(slow)
    assert mon.inertial is False and len([n for n in of(events, Notice) if "at rest over" in n.text]) == 1
    assert not texts(low(drive(60.0, speed=5.0, seed=8)))
