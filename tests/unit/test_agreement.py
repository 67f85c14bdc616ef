"""guard.runtime.agreement on samples made here: a vehicle circling at a known speed and yaw rate, its
accelerometers off by a known bias in its own axes, the filter's heading given at each fix. The bias
comes out, each axis with its sign, at every window, through the turn; a hole in the IMU, time going
back and values that are not numbers are left out, never measured."""

import math
import re

import numpy as np
import pytest

from guard.core.ekf import N_STATES, TH
from guard.model.events import Estimate
from guard.model.samples import GnssFix, ImuSample
from guard.runtime.agreement import (LIVE_CHECK_S, LIVE_KEEP_S, LIVE_MIN_PAIRS, LIVE_SEGMENTS, SAY_WINDOW_S, TRACK,
                                     WANDER_SAY_MPS2, Agreement, LiveWander)

IMU_HZ, FIX_HZ = 50, 10
SPEED, YAW_RATE = 6.0, 0.3      # m/s, rad/s (ENU: counter-clockwise): 2.4 rad in 8 s


def estimate(t_us: int, yaw: float) -> Estimate:
    x = np.zeros(N_STATES)
    x[TH] = yaw
    return Estimate(t_us, 0, 0.0, 0.0, yaw, x, np.zeros(N_STATES), (0.0, 0.0, 0.0))


def circle(bias: tuple[float, float], seconds: float = 60.0, t0: float = 0.0, hole: tuple[float, float] = (0, 0),
           nan_at: float | None = None, theta0: float = 0.4):
    """(sample or None, events) in time order: the IMU at IMU_HZ, a fix and the filter's heading at FIX_HZ.
    `bias`: (forward, left), or a function of the time that gives it."""
    out = []
    for i in range(int(seconds * IMU_HZ) + 1):
        t = t0 + i / IMU_HZ
        th = theta0 + YAW_RATE * (t - t0)
        if not hole[0] <= t - t0 < hole[1]:
            b = bias(t) if callable(bias) else bias
            fwd, left = b[0], SPEED * YAW_RATE + b[1]              # the centripetal force, to the left
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


def stepping(size: float, seed: int, every_s: float = 8.0):
    """A bias that takes a new value, N(0, size) per axis, every every_s."""
    rng = np.random.default_rng(seed)
    draws = rng.normal(0.0, size, (1000, 2))
    return lambda t: tuple(draws[int(t // every_s) % len(draws)])


def live(stream, wander=None):
    """LiveWander fed the stream (or `wander` fed more of it); with the lines it said, all of them."""
    w = wander or LiveWander(lambda line: w.lines.append(line))
    if wander is None:
        w.lines = []
    for sample, events in stream:
        w.on_sample(sample)
        w.on_events(events)
    return w, w.lines


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_guard_run_says_a_wander_once_after_enough_windows_and_lets_go(seed):
    """An error that steps every 8 s by 0.5 m/s^2 per axis: not said at the first minute's check (fewer
    than LIVE_MIN_PAIRS adjacent windows), said at the second with its size near the offline measure's,
    once; what it held let go, and what comes after not listened to."""
    stream = circle(stepping(0.5, seed), seconds=130.0)
    w, said = live(stream)
    assert len(said) == 1, said
    assert 100e6 <= w.said_us <= 130e6, w.said_us                  # the second check, at 120 s of the IMU's clock
    assert w.done and not w.segments and not w.track and not w.fixes and w.checked[1] >= LIVE_MIN_PAIRS
    heard = [(x, e) for x, e in stream if x.t_us <= w.said_us]     # what it had heard when it said it
    offline = {r["window_s"]: r for r in run(heard).measure()}[SAY_WINDOW_S]["allan_mps2"]
    size = float(re.search(r"wander ([0-9.]+) m/s\^2", said[0]).group(1))
    assert size == pytest.approx(offline, abs=0.01) and size > WANDER_SAY_MPS2
    w, said = live(circle(stepping(0.5, seed), seconds=130.0, t0=130.0), w)
    assert len(said) == 1 and not w.segments


@pytest.mark.parametrize("bias", [(0.0, 0.0), (0.4, -0.3), "small"])
def test_guard_run_says_nothing_of_a_constant_or_small_error_and_holds_ten_minutes_at_most(bias):
    """A constant bias, however large, does not wander; one stepping by 0.05 per axis stays under
    WANDER_SAY_MPS2. Over 25 minutes the check measures every minute and holds the latest LIVE_KEEP_S."""
    stream = circle(stepping(0.05, 4) if bias == "small" else bias, seconds=1500.0)
    w, said = live(stream)
    assert not said and not w.done
    adev, pairs = w.checked
    assert pairs >= 60 and adev < WANDER_SAY_MPS2 / 2, w.checked
    held = np.frombuffer(w.track, dtype=float)[0::len(TRACK)]
    assert held[-1] - held[0] <= LIVE_KEEP_S + LIVE_CHECK_S + 1.0, (held[0], held[-1])
    fixes = np.frombuffer(w.fixes, dtype=float)[0::3]
    assert fixes[-1] - fixes[0] <= LIVE_KEEP_S + LIVE_CHECK_S + 1.0


@pytest.mark.parametrize("boot_s", [40.0, 90.0])
def test_guard_run_keeps_few_stretches_across_reboots_and_checks_on_the_new_clock(boot_s):
    """Thirty reboots, each under a check's minute (a boot loop) or over it: at most LIVE_SEGMENTS stretches
    held; a clock that went back is checked a minute after it restarted, and a wander that follows is
    still said."""
    stream = []
    for i in range(30):
        stream += circle((0.1, 0.0), seconds=boot_s, t0=5.0 + 0.01 * i)
    w, said = live(stream)
    assert not said and len(w.segments) <= LIVE_SEGMENTS
    w, said = live(circle(stepping(0.5, 5), seconds=130.0, t0=2.0), w)
    assert len(said) == 1 and w.said_us >= 2e6 + LIVE_CHECK_S * 1e6, (said, w.checked)


@pytest.mark.parametrize("first_s, then_s", [(300.0, 720.0), (480.0, 240.0)])
def test_guard_run_holds_the_latest_ten_minutes_across_a_reboot(first_s, then_s):
    """A reboot after first_s, then then_s more: what it holds is the latest LIVE_KEEP_S of the samples'
    time (up to a check's minute more), the new stretch first and the old one back from its end for
    what is left, gone once the new one fills it."""
    stream = circle((0.3, 0.1), seconds=first_s) + circle((0.3, 0.1), seconds=then_s, t0=5.0, theta0=1.0)
    w, said = live(stream)
    assert not said
    spans = [t[-1] - t[0] for track, _ in w.segments if len(t := np.frombuffer(track, dtype=float)[0::len(TRACK)])]
    assert sum(spans) <= LIVE_KEEP_S + LIVE_CHECK_S + 1.0, spans
    assert len(spans) == (1 if then_s > LIVE_KEEP_S else 2), spans
    if len(spans) == 2:
        assert spans[0] >= LIVE_KEEP_S - then_s - 1.0, spans       # the old stretch's latest part kept


def test_guard_run_s_figure_is_that_of_the_latest_ten_minutes():
    """An error stepping by 0.1 per axis (under WANDER_SAY_MPS2, never said) for 15 minutes, then by
    0.03: the last check's figure is the offline measure of the ten minutes before it, not of the whole."""
    stream = circle(lambda t: stepping(0.1, 8)(t) if t < 900.0 else stepping(0.03, 9)(t), seconds=1320.0)
    w, said = live(stream)
    assert not said
    t_check = w.checked_us
    latest = [(x, e) for x, e in stream if t_check - LIVE_KEEP_S * 1e6 <= x.t_us <= t_check]
    offline = {r["window_s"]: r for r in run(latest).measure()}[SAY_WINDOW_S]["allan_mps2"]
    whole = {r["window_s"]: r for r in run(stream).measure()}[SAY_WINDOW_S]["allan_mps2"]
    assert w.checked[0] == pytest.approx(offline, abs=0.005) and abs(w.checked[0] - whole) > 0.03, \
        (w.checked, offline, whole)


def test_a_check_comes_once_a_period_of_the_samples_time_and_starts_again_after_a_reboot():
    """Every: due once per period of sample time (not per sample, not per second of the wall); a clock
    gone back by more than a period (a reboot) starts the period again, one gone back less does not."""
    from guard.runtime.every import Every
    every = Every(60.0)
    due = [t for t in range(0, 200_000_000, 500_000) if every.due(t)]
    assert due == [60_000_000, 120_000_000, 180_000_000]
    assert not every.due(150_000_000) and every.due(240_000_000), "a sample out of order: the period holds"
    assert not every.due(1_000_000) and not every.due(60_000_000) and every.due(61_000_000), \
        "after a reboot the period starts at its first sample"
