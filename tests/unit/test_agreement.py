"""guard.runtime.agreement on samples made here: a vehicle circling at a known speed and yaw rate, its
accelerometers off by a known bias in its own axes, the filter's heading given at each fix. The bias
comes out, each axis with its sign, at every window, through the turn; a hole in the IMU, time going
back and values that are not numbers are left out, never measured."""

import math

import numpy as np
import pytest

from guard.core.ekf import N_STATES, TH
from guard.model.events import Estimate
from guard.model.samples import GnssFix, ImuSample
from guard.runtime.agreement import Agreement

IMU_HZ, FIX_HZ = 50, 10
SPEED, YAW_RATE = 6.0, 0.3      # m/s, rad/s (ENU: counter-clockwise): 2.4 rad in 8 s


def estimate(t_us: int, yaw: float) -> Estimate:
    x = np.zeros(N_STATES)
    x[TH] = yaw
    return Estimate(t_us, 0, 0.0, 0.0, yaw, x, np.zeros(N_STATES), (0.0, 0.0, 0.0))


def circle(bias: tuple[float, float], seconds: float = 60.0, t0: float = 0.0, hole: tuple[float, float] = (0, 0),
           nan_at: float | None = None, theta0: float = 0.4):
    """(sample or None, events) in time order: the IMU at IMU_HZ, a fix and the filter's heading at FIX_HZ."""
    out = []
    for i in range(int(seconds * IMU_HZ) + 1):
        t = t0 + i / IMU_HZ
        th = theta0 + YAW_RATE * (t - t0)
        if not hole[0] <= t - t0 < hole[1]:
            fwd, left = bias[0], SPEED * YAW_RATE + bias[1]        # the centripetal force, to the left
            if nan_at is not None and abs(t - t0 - nan_at) < 1e-9:
                fwd = math.nan
            # FRD body axes: y to the right, z down (a yaw counter-clockwise seen from above: -z)
            out.append((ImuSample(int(t * 1e6), fwd, -left, -9.81, 0.0, 0.0, -YAW_RATE, None, None, None), []))
        if i % (IMU_HZ // FIX_HZ) == 0:
            fix = GnssFix(int(t * 1e6), True, 47.0, 8.0, 400.0, SPEED * math.sin(th), SPEED * math.cos(th), 0.8, 0.1)
            out.append((fix, [estimate(int(t * 1e6), math.remainder(th, math.tau))]))
    return out


def run(stream) -> Agreement:
    a = Agreement()
    for sample, events in stream:
        a.on_sample(sample)
        a.on_events(events)
    return a


def body_error(a: Agreement, window_s: float) -> np.ndarray:
    from guard.runtime.agreement import discrepancies, rows
    parts = [discrepancies(r, window_s)[0] for track, fixes in a.segments if len(r := rows(track, fixes)) >= 2]
    return np.concatenate(parts)


@pytest.mark.parametrize("bias", [(0.0, 0.0), (0.4, 0.0), (0.0, -0.3), (-0.25, 0.35)])
def test_a_bias_in_the_vehicle_s_axes_comes_out_with_its_sign_through_the_turn(bias):
    a = run(circle(bias))
    for w in (0.4, 1.0, 4.0, 8.0):
        e = body_error(a, w)
        assert len(e) >= 5
        assert np.allclose(e, bias, atol=0.02), (w, e.mean(axis=0))
    rows = {r["window_s"]: r for r in a.measure()}
    assert rows[8.0]["rms_mps2"] == pytest.approx(math.hypot(*bias), abs=0.02)
    assert rows[8.0]["allan_mps2"] < 0.02
    # the GNSS's mean acceleration over a window: the centripetal one, averaged as it turns with the heading
    for w in (0.4, 8.0):
        turned = YAW_RATE * w
        assert rows[w]["gnss_accel_rms_mps2"] == pytest.approx(SPEED * YAW_RATE * math.sin(turned / 2) / (turned / 2),
                                                               rel=0.02)


def test_a_hole_in_the_imu_leaves_its_windows_out_and_time_going_back_starts_again():
    bias = (0.3, 0.1)
    stream = circle(bias, seconds=60.0, hole=(20.0, 26.0))
    # the autopilot rebooted: its clock starts again at 5 s, the vehicle still circling
    stream += circle(bias, seconds=40.0, t0=5.0, theta0=1.1)
    a = run(stream)
    assert len(a.segments) == 2
    whole = circle(bias, seconds=60.0) + circle(bias, seconds=40.0, t0=5.0, theta0=1.1)
    rows, rows_whole = ({r["window_s"]: r for r in x.measure()} for x in (a, run(whole)))
    assert rows[8.0]["left_out"] >= 1 and rows[8.0]["windows"] < rows_whole[8.0]["windows"]
    for w in (1.0, 8.0):
        assert np.allclose(body_error(a, w), bias, atol=0.02), w     # nothing measured across the hole or the reboot


def test_a_sample_that_is_not_a_number_is_not_integrated():
    a = run(circle((0.2, 0.0), nan_at=30.0))
    assert all(math.isfinite(v) for v in a.track)
    rows = {r["window_s"]: r for r in a.measure()}
    assert rows[8.0]["rms_mps2"] == pytest.approx(0.2, abs=0.02)


def test_nothing_to_measure_is_none():
    assert Agreement().measure() is None
    a = Agreement()
    a.on_sample(GnssFix(1_000_000, True, 47.0, 8.0, 400.0, 1.0, 0.0, 0.8, 0.1))
    assert a.measure() is None


def test_a_stale_fix_after_a_reboot_or_a_jittering_imu_loses_nothing_and_a_tiny_window_ends():
    bias = (0.3, 0.1)
    before = circle(bias, seconds=30.0)
    after = circle(bias, seconds=40.0, t0=5.0, theta0=1.1)
    # the receiver's next fix still on the clock before the reboot, arriving after it
    stale = GnssFix(int(29.95e6), True, 47.0, 8.0, 400.0, 0.0, SPEED, 0.8, 0.1)
    a = run(before + after[:1] + [(stale, [])] + after[1:])
    clean = run(before + after)
    assert {r["window_s"]: r["windows"] for r in a.measure()} == {r["window_s"]: r["windows"] for r in clean.measure()}
    # an IMU sample stamped 2 ms early, among the others: left out, no new segment
    jitter = circle(bias, seconds=30.0)
    t, s = jitter[500]
    jitter.insert(501, (ImuSample(t.t_us - 2000, *[getattr(t, f) for f in ImuSample.__slots__[1:]]), [])
                  if isinstance(t, ImuSample) else (t, s))
    assert len(run(jitter).segments) == 1
    assert run(circle(bias, seconds=10.0)).measure((0.0005,)) is None      # no window that short: and it ends
