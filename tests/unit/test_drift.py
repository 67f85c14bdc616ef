"""The IMU's open-loop drift, measured in flight (guard.core.drift): the probes' shared dead reckoning,
what they measure, and what the judge does with it."""

import math

import numpy as np
import pytest

from guard.core.drift import EDGES_S, F_MAX, TAU_S, Drift
from guard.core.ekf import BAX, BAY, N_STATES, TH, VX, VY, X, Y
from guard.core.monitor import Monitor, MonitorConfig
from guard.model.events import Alarm, Cleared, Estimate, Notice
from guard.model.samples import VehicleType
from unit.synthetic import T0_US, drive, of


def _state(e, n, theta, vx, vy, bx, by):
    x = np.zeros(N_STATES)
    x[X], x[Y], x[TH], x[VX], x[VY], x[BAX], x[BAY] = e, n, theta, vx, vy, bx, by
    return x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_core_drift_probes_share_one_dead_reckoning_that_is_each_probes_own(seed):
    """Each probe's position from the shared sums is the one its own double integration gives:
    the specific force less its biases, turned by the heading, at uneven steps."""
    rng = np.random.default_rng(seed)
    d = Drift()
    t_us, own = 1_000_000, []
    d.imu(t_us, 0.0, 0.0, 0.0)
    for i in range(600):
        t_us += int(rng.integers(10_000, 30_000))
        theta = float(rng.uniform(-math.pi, math.pi)) if i % 50 == 0 else theta
        ax, ay = rng.normal(0.0, 1.0, 2)
        if i in (40, 170, 333):         # a probe starts: where the filter puts the vehicle, its biases
            x = _state(*rng.normal(0.0, 5.0, 2), theta, *rng.normal(0.0, 3.0, 2), *rng.normal(0.0, 0.3, 2))
            d.start(t_us, x)
            # a probe starts at the last fusion's time, the estimate carried back to it by its velocity
            cs, sn = math.cos(theta), math.sin(theta)
            v = np.array([x[VX] * cs - x[VY] * sn, x[VX] * sn + x[VY] * cs])
            back = (t_us - d.t_us) / 1e6
            own.append([d.t_us, np.array([x[X], x[Y]]) - v * back, v, np.array([x[BAX], x[BAY]])])
            d._last_start = None        # the next one may start at once
        dt = (t_us - d.t_us) / 1e6
        d.imu(t_us, float(ax), float(ay), theta)
        c, s = math.cos(theta), math.sin(theta)
        for p in own:
            if p[0] < t_us:
                f = np.array([ax, ay]) - p[3]
                a = np.array([c * f[0] - s * f[1], s * f[0] + c * f[1]])
                p[1] = p[1] + p[2] * dt + 0.5 * a * dt * dt
                p[2] = p[2] + a * dt
    assert len(d.probes) == 3
    for probe, p in zip(d.probes, own):
        assert np.allclose(d.position(probe, d.t_us), p[1], atol=1e-6)


def _at_rest(d, b, seconds, t_us=0, gap_at=None):
    """A vehicle at rest at the origin whose levelled accelerometer reads b (m/s^2) more than it is,
    IMU at 50 Hz, a fix at 5 Hz (each starting a probe from the filter's estimate: no bias learnt);
    `gap_at`: the IMU silent for 3 s from then (s). Returns the time reached."""
    for i in range(1, int(seconds * 50)):
        t_us += 20_000
        if gap_at is not None and gap_at * 1e6 <= t_us < (gap_at + 3) * 1e6:
            continue
        d.imu(t_us, b, 0.0, 0.3)
        if i % 10 == 0:
            d.fix(t_us, (0.0, 0.0), calm=True)
            d.start(t_us, _state(0.0, 0.0, 0.3, 0.0, 0.0, 0.0, 0.0))
    return t_us


def test_core_drift_measures_an_accelerometer_error_the_filter_does_not_know():
    """A vehicle at rest whose levelled accelerometer reads b more than it is: a probe started from
    the filter's estimate (no bias learnt) strays by b t^2 / 2, and the drift measured at each age is
    that, within the bins' width; a test not calm teaches it nothing; widened() keeps within
    [the filter's sigma, F_MAX times it]."""
    b, d = 0.2, Drift()
    t_us = _at_rest(d, b, 400)
    for lo, hi in zip(EDGES_S, EDGES_S[1:]):
        # the rms of b t^2 / 2 over the ages at which the fixes meet the probes in [lo, hi)
        ages = np.arange(round(lo / 0.2), round(hi / 0.2)) * 0.2
        expected = math.sqrt(np.mean((0.5 * b * ages ** 2) ** 2))
        mid = math.sqrt(lo * hi)
        assert d.sigma(mid) == pytest.approx(expected, rel=0.1)
    d.restart()                           # what the running probes measured is taken
    before = list(d.ms)
    for i in range(50 * 40):              # 40 s of probes meeting fixes 100 m off, none of them calm
        t_us += 20_000
        d.imu(t_us, b, 0.0, 0.3)
        if i % 10 == 0:
            d.fix(t_us, (100.0, 100.0), calm=False)
            d.start(t_us, _state(0.0, 0.0, 0.3, 0.0, 0.0, 0.0, 0.0))
    assert len(d.probes) > 3
    d.restart()
    assert d.ms == before
    for sigma_model in (0.5, 3.0, 50.0):
        w = d.widened(sigma_model, 20.0)
        assert sigma_model <= w <= F_MAX * sigma_model
    assert d.widened(0.5, 20.0) == F_MAX * 0.5 and d.widened(50.0, 20.0) == 50.0
    assert Drift().widened(3.0, 20.0) == 3.0      # nothing measured: the filter's own


def test_core_drift_forgets_over_its_memory_and_not_faster():
    """Each bin takes one sample per probe, forgetting over TAU_S: after an error of 0.2 m/s^2 for 10
    minutes, one of 0.1 is at first a small part of the bins' figure (a probe's weight, 5 s of 300)
    and has replaced it after three memories."""
    d, ref = Drift(), Drift()
    _at_rest(ref, 0.1, 600)
    t_us = _at_rest(d, 0.2, 600)
    t_us = _at_rest(d, 0.1, 60, t_us)
    early = d.sigma(24.0) / ref.sigma(24.0)
    _at_rest(d, 0.1, 3 * TAU_S, t_us)
    late = d.sigma(24.0) / ref.sigma(24.0)
    assert early > 1.5 and late == pytest.approx(1.0, rel=0.1)


def test_core_drift_interpolates_between_its_bins_and_grows_past_them_as_a_bias_does():
    d = Drift()
    d.n = [10] * len(d.n)
    d.ms = [(2.0 ** k) ** 2 for k in range(len(d.ms))]      # 1, 2, 4, 8, 16 m at the bins' middles
    mids = [math.sqrt(a * b) for a, b in zip(EDGES_S, EDGES_S[1:])]
    for k, mid in enumerate(mids):
        assert d.sigma(mid) == pytest.approx(2.0 ** k)
    assert d.sigma(math.sqrt(mids[1] * mids[2])) == pytest.approx(math.sqrt(2.0 * 4.0))   # log-log
    assert d.sigma(mids[0] / 2) == pytest.approx(0.5)                # with the age before the first
    assert d.sigma(2 * mids[-1]) == pytest.approx(4 * 16.0)          # with its square after the last
    d.n[0] = 2                                                       # a bin not yet believed
    assert d.sigma(mids[0]) == pytest.approx(mids[0] / mids[1] * 2.0)


def test_core_drift_is_not_dead_reckoned_across_an_imu_gap():
    """The IMU silent for 3 s: what the vehicle did then is unknown, and the probes running end there
    instead of holding the last acceleration over the gap."""
    d = Drift()
    _at_rest(d, 0.0, 60, gap_at=40.0)
    assert d.sigma(24.0) < 0.01


class _Unmeasured(Drift):
    """The control: a drift never measured (the judge then has the filter's uncertainty alone)."""

    def sigma(self, age_s):
        return None


def _spoofed(seed, wander_mps2, measured=True, vehicle="auto"):
    """An air vehicle whose accelerometer errs by a slow sinusoid the filter's model has not (a
    copter's tilt error over its manoeuvres), vibrating, its GNSS velocity spoofed 2 m/s east from
    100 s on (the position with it). Returns the events and the monitor."""
    samples = drive(110, seed=seed, vibration=lambda t: 0.5,
                    accel_bias=lambda t: wander_mps2 * math.sin(2 * math.pi * t / 60.0),
                    gnss_offset=lambda t: (2.0 * (t - 100.0), 0.0) if t >= 100.0 else (0.0, 0.0),
                    vel_offset=lambda t: (2.0, 0.0) if t >= 100.0 else (0.0, 0.0))
    mon = Monitor(MonitorConfig(declination_deg=0.0, vehicle=vehicle))
    if not measured:
        mon.drift = _Unmeasured()
    return [e for s in samples for e in mon.step(s)], mon


def _coast(events):
    """The first alarm's time, the first re-anchoring's after it, and the estimate's largest error from
    the truth (the vehicle at 5 m/s east from the origin, drive()'s) between them."""
    t_alarm = of(events, Alarm)[0].t_us
    t_anchor = next(e.t_us for e in of(events, Notice) if "confirmed or refuted" in e.text and e.t_us >= t_alarm)
    errors = [math.hypot(e.east_m - 5.0 * (e.t_us - T0_US) / 1e6, e.north_m)
              for e in of(events, Estimate) if t_alarm <= e.t_us < t_anchor]
    return t_alarm, t_anchor, max(errors, default=0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_core_an_imu_measured_to_drift_is_not_coasted_on_past_what_it_can_hold(seed):
    """A GNSS velocity alarm rewinds the filter up to 20 s and coasts on the IMU alone. With a wander
    of 0.15 m/s^2 the IMU alone strays 33 to 41 m (rms) in 16 to 32 s while the filter's model says
    13 m at the alarm: coasted, the estimate stood up to 17 to 29 m from the vehicle over 5 s. The
    drift measured before the attack says so, and the estimate is re-anchored at the alarm (on the
    spoofer's fix, 0 m off then), its alarm standing."""
    events, mon = _spoofed(seed, 0.15)
    t_alarm, t_anchor, worst = _coast(events)
    assert of(events, Alarm)[0].sensor == "gnss_vel" and abs(t_alarm / 1e6 - 101.0) < 0.5
    assert t_anchor - t_alarm <= 200_000 and worst < 2.0
    assert not [e for e in of(events, Cleared) if e.t_us >= t_alarm]           # the alarm stands
    assert "gnss_vel" in mon.alarmed
    said = [e.text for e in of(events, Notice) if "confirmed or refuted" in e.text]
    assert "as far as its IMU drifts in this flight" in said[0]       # why, for the operator
    control, _ = _spoofed(seed, 0.15, measured=False)
    c_alarm, c_anchor, c_worst = _coast(control)
    assert c_anchor - c_alarm >= 4_000_000 and c_worst > 15.0
    assert not any("drifts" in e.text for e in of(control, Notice))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_core_an_imu_as_its_model_says_is_coasted_on_as_before(seed):
    """The same spoof on a vehicle whose accelerometer errs as the model says (white vibration only):
    the drift measured is within what the filter expects, and the coast lasts as long as without it
    (what a patient attacker's offset needs to be taken is not shortened)."""
    events, _ = _spoofed(seed, 0.0)
    control, _ = _spoofed(seed, 0.0, measured=False)
    t_alarm, t_anchor, _ = _coast(events)
    c_alarm, c_anchor, _ = _coast(control)
    assert t_alarm == c_alarm and abs(t_anchor - c_anchor) <= 400_000 and c_anchor - c_alarm >= 4_000_000


def test_core_a_vehicle_found_to_be_on_wheels_coasts_on_the_filter_s_uncertainty():
    """The autopilot's word that the vehicle is on wheels, after its drift was measured in the air:
    its coast is held by its sideways constraint, and the drift measured is not applied to it."""
    samples = drive(110, seed=0, vibration=lambda t: 0.5,
                    accel_bias=lambda t: 0.15 * math.sin(2 * math.pi * t / 60.0),
                    gnss_offset=lambda t: (2.0 * (t - 100.0), 0.0) if t >= 100.0 else (0.0, 0.0),
                    vel_offset=lambda t: (2.0, 0.0) if t >= 100.0 else (0.0, 0.0))
    at = next(i for i, s in enumerate(samples) if s.t_us >= T0_US + 95_000_000)
    mon = Monitor(MonitorConfig(declination_deg=0.0))
    events = [e for s in samples[:at] + [VehicleType(ground=True)] + samples[at:] for e in mon.step(s)]
    assert sum(mon.drift.n) > 0 and of(events, Alarm)
    assert not any("drifts" in e.text for e in of(events, Notice))


def test_core_a_wheeled_vehicle_s_drift_is_not_measured():
    """A ground vehicle's coast is held by its sideways constraint, which a dead reckoning of its
    accelerometers has not: no probe runs."""
    _, mon = _spoofed(0, 0.15, vehicle="ground")
    assert sum(mon.drift.n) == 0 and not mon.drift.probes
