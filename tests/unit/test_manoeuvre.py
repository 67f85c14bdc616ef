"""On GNSS alone, the IMU's word on how much the acceleration changed (guard.core.aiding.manoeuvre):
the change of the mean horizontal specific force from one fix interval to the next, in a frame the
gyro turns, beyond the accelerometers' own noise, widens the acceleration's random walk at that fix."""

import math

import numpy as np
import pymap3d
import pytest

from guard.core.aiding import manoeuvre
from guard.core.aiding.manoeuvre import AccelChange
from guard.core.monitor import MonitorConfig
from guard.model.events import Alarm, Tested
from guard.model.samples import GnssFix, ImuSample
from unit.synthetic import ALT0, G, GNSS_EVERY, IMU_DT_US, LAT0, LON0, T0_US, of, run

AIR = MonitorConfig(declination_deg=0.0, vehicle="air")


def intervals(change, samples_of, fixes, noise_var=0.0, per_fix=10, dt_us=20_000):
    """Feed `fixes` intervals of `per_fix` samples (samples_of(t) -> ax, ay, rate) and return each
    fix's da."""
    out, t = [], 0
    for _ in range(fixes):
        for _ in range(per_fix):
            t += dt_us
            change.add(t, *samples_of(t / 1e6))
        out.append(change.change(t, noise_var))
    return out


def test_a_steady_turn_s_acceleration_turns_by_what_the_gyro_says():
    """A constant 5 m/s^2 to the left in a turn of 0.5 rad/s: in the ground's frame it turns 0.1 rad a
    0.2 s interval, a change of 2 a sin(w T / 2) between the intervals' means; a straight line's none."""
    da = intervals(AccelChange(), lambda t: (0.0, 5.0, 0.5), 20)
    assert da[0] == 0.0                                 # nothing before the first interval
    assert da[1:] == pytest.approx([2 * 5.0 * math.sin(0.05)] * 19, rel=0.02)
    assert intervals(AccelChange(), lambda t: (1.0, 2.0, 0.0), 10) == pytest.approx([0.0] * 10, abs=1e-12)


def test_a_reversal_is_its_whole_change_and_noise_alone_is_mostly_nothing():
    """A bank to the other side (the turn's acceleration from +10 to -10 m/s^2) is 20 m/s^2 at the fix
    after it; the accelerometers' noise alone, its variance given, reads 0 at most fixes and never much."""
    change = AccelChange()
    da = intervals(change, lambda t: (0.0, 10.0 if t <= 1.0 else -10.0, 0.0), 10)
    assert da[4] == pytest.approx(0.0, abs=1e-9) and da[5] == pytest.approx(20.0, rel=1e-6)
    rng = np.random.default_rng(3)
    sigma = 0.8
    noisy = intervals(AccelChange(), lambda t: (*rng.normal(0.0, sigma, 2), 0.0), 400, noise_var=2 * sigma ** 2)
    assert np.mean(np.array(noisy) == 0.0) > 0.4
    assert np.percentile(noisy, 95) < 1.5 * sigma


def test_blows_gaps_and_silent_intervals_give_nothing():
    """A specific force over 3 g is left out of the means; an interval without a sample, or two
    intervals more than MAX_APART_S apart, are no change."""
    change = AccelChange()
    da = intervals(change, lambda t: (0.0, 50.0 if 0.5 < t < 0.52 else 2.0, 0.0), 6)
    assert da == pytest.approx([0.0] * 6, abs=1e-12)
    assert change.change(10_000_000, 0.0) == 0.0        # nothing heard since the last fix
    change.add(10_000_000 + int(manoeuvre.MAX_APART_S * 1e6), 9.0, 0.0, 0.0)
    assert change.change(10_000_000 + int(manoeuvre.MAX_APART_S * 1e6) + 1, 0.0) == 0.0


def weave(duration_s, seed, speed=12.0, rate=1.6, period=1.5, start_s=20.0, vel_offset=None, gnss_offset=None,
          imu_every=1):
    """An air vehicle without a compass at 12 m/s whose track swings from side to side from start_s: its
    turn rate rate * sin(2 pi t / period), its acceleration across the track up to speed * rate (19 m/s^2,
    reversed every 0.75 s: a small plane's wing-overs). IMU 50 Hz (every imu_every-th sample kept), GNSS
    5 Hz; vel_offset(t) and gnss_offset(t) -> (east, north) added to the fixes."""
    rng = np.random.default_rng(seed)
    e = n = 0.0
    psi, dt = 0.4, IMU_DT_US / 1e6
    out = []
    for i in range(int(duration_s / dt) + 1):
        t_us, t = T0_US + i * IMU_DT_US, i * dt
        w = rate * math.sin(2 * math.pi * (t - start_s) / period) if t >= start_s else 0.0
        if i % GNSS_EVERY == 0:
            dve, dvn = vel_offset(t) if vel_offset else (0.0, 0.0)
            de, dn = gnss_offset(t) if gnss_offset else (0.0, 0.0)
            lat, lon, _ = pymap3d.enu2geodetic(e + de + rng.normal(0, 0.1), n + dn + rng.normal(0, 0.1), 0.0,
                                               LAT0, LON0, ALT0)
            out.append(GnssFix(t_us, True, float(lat), float(lon), ALT0,
                               speed * math.sin(psi) + dvn + rng.normal(0, 0.03),
                               speed * math.cos(psi) + dve + rng.normal(0, 0.03), 0.5, 0.1))
        a = rng.normal(0.0, 0.3, 3)
        if i % imu_every == 0:      # FRD: a turn to the left (w > 0) is a specific force to the left, -y
            out.append(ImuSample(t_us, a[0], -speed * w + a[1], -G + a[2], 0.0, 0.0, -w + rng.normal(0, 0.001),
                                 None, None, None))
        mid = psi + w * dt / 2
        e, n, psi = e + speed * math.cos(mid) * dt, n + speed * math.sin(mid) * dt, psi + w * dt
    return out


def gnss_peaks(events):
    peaks = {}
    for ev in of(events, Tested):
        ratio = max([s / h for s, h in zip(ev.statistic, ev.threshold) if 0.0 < h < math.inf], default=0.0)
        sensor = ev.innovation.sensor.value
        peaks[sensor] = max(peaks.get(sensor, 0.0), ratio)
    return peaks


@pytest.mark.parametrize("seed", [1, 2])
def test_wing_overs_the_imu_saw_are_no_gnss_alarm(seed, monkeypatch):
    """On GNSS alone, the weave's reversals are a GNSS velocity that jumps against a random walk of
    5 m/s^2/sqrt(s): without the IMU's word the same flight raises an alarm at every swing (as two real
    ArduPlane flights without a compass did); with it, none, the tests far from their thresholds."""
    mon, events = run(weave(60.0, seed), AIR)
    assert mon.inertial is False and not of(events, Alarm)
    assert gnss_peaks(events)["gnss_vel"] < 0.5
    # the fixes tested against the widened model are counted (most of the 40 s of weaving's 200)
    assert 100 < mon.adjusted["gnss_manoeuvre_widened"] <= 200
    straight, _ = run(weave(60.0, seed, rate=0.0), AIR)
    assert straight.adjusted["gnss_manoeuvre_widened"] == 0
    monkeypatch.setattr(AccelChange, "change", lambda self, t_us, noise_var: 0.0)
    _, unheard = run(weave(60.0, seed), AIR)
    assert len([a for a in of(unheard, Alarm) if a.sensor.value == "gnss_vel"]) >= 10


@pytest.mark.parametrize("seed", [1, 2])
def test_gnss_attacks_in_the_wing_overs_are_still_caught(seed):
    """The IMU cannot move with a GNSS attack: a 5 m step in the fixes is caught at once and a 2 m/s
    step in their velocity alone within 2 s (the position it no longer integrates to), mid-weave."""
    onset = 40.0
    step = run(weave(60.0, seed, gnss_offset=lambda t: (0.0, 5.0) if t >= onset else (0.0, 0.0)), AIR)[1]
    first = [a for a in of(step, Alarm) if a.t_us >= T0_US + onset * 1e6][0]
    assert first.sensor.value == "gnss_pos" and first.t_us - (T0_US + onset * 1e6) <= 0.2e6
    vel = run(weave(60.0, seed, vel_offset=lambda t: (0.0, 2.0) if t >= onset else (0.0, 0.0)), AIR)[1]
    late = [a for a in of(vel, Alarm) if a.t_us >= T0_US + onset * 1e6]
    assert late and late[0].sensor.value in ("gnss_pos", "gnss_vel")
    assert late[0].t_us - (T0_US + onset * 1e6) <= 2e6
    assert not [a for a in of(vel, Alarm) if a.t_us < T0_US + onset * 1e6]


def test_a_stream_too_slow_to_integrate_says_nothing_of_the_acceleration():
    """At 2 Hz the IMU's samples are points, not means (a telemetry link's RAW_IMU): its vibration and
    the attitude's lag would read as changes of several m/s^2, so such a stream is not heard."""
    mon, _ = run(weave(40.0, 1, imu_every=25), AIR)
    assert mon.inertial is False and mon.imu_rate.fast is False
    assert mon.manoeuvre.last is None and mon.manoeuvre.n == 0
