"""guard.runtime.position_wander: a receiver's position less its own velocity's integral, measured
against known errors written here (white, a random walk, a drift), on a moving vehicle whose velocity
the integral must take out, and across a gap and a reboot; the line guard replay says; and guard run's
live check (LivePositionWander): said once, of the latest ten minutes, bounded through a boot loop."""

import math

import numpy as np
import pytest

from guard.core.ekf import Q_POS_MAX, FilterConfig
from guard.model.samples import GnssFix
from guard.runtime.position_wander import (LIVE_CHECK_S, LIVE_KEEP_S, LIVE_MIN_SPAN_S, LIVE_SEGMENTS, MIN_PAIRS,
                                           SAY_LAG_S, SAY_RATIO, LivePositionWander, PositionWander, beyond_tune, model,
                                           ratio_at, said, structure, tunable)
from guard.runtime.tune import position_walk

HZ = 5.0
LAT0, LON0 = 47.397742, 8.545594


def series(seconds, error, speed=(3.0, -2.0), seed=0):
    """t, the true track plus error(t, rng) (m, east north), and the true velocity (exact)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / HZ)
    v = np.tile(speed, (len(t), 1))
    return t, v * t[:, None] + error(t, rng), v


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_white_noise_reads_its_sigma_a_random_walk_its_q_and_a_drift_grows_as_the_lag(seed):
    n = int(2000 * HZ)
    t, en, v = series(2000.0, lambda t, rng: rng.normal(0.0, 0.4, (len(t), 2)), seed=seed)
    for lag, d in structure(t, en, v).items():
        assert d == pytest.approx(0.4, rel=0.08), lag
    q = 0.3
    t, en, v = series(2000.0, lambda t, rng: np.cumsum(rng.normal(0.0, q / math.sqrt(HZ), (n, 2)), axis=0),
                      seed=seed)
    for lag, d in structure(t, en, v).items():
        assert d == pytest.approx(q * math.sqrt(lag / 2.0), rel=0.25), lag
    t, en, v = series(2000.0, lambda t, rng: 0.05 * t[:, None] * np.array([1.0, -1.0]) +
                      rng.normal(0.0, 0.01, (len(t), 2)), seed=seed)
    d = structure(t, en, v)
    assert d[80.0] / d[10.0] == pytest.approx(8.0, rel=0.05), "a drift grows as the lag"


def test_pairs_across_a_gap_or_a_reboot_are_not_taken():
    """Two stretches whose positions jump 50 m apart (a reboot, or a gap over MAX_GAP_S): within each
    the receiver is exact, and no pair spans the two."""
    t, en, v = series(100.0, lambda t, rng: np.zeros((len(t), 2)))
    half = len(t) // 2
    en[half:] += 50.0
    stretch = np.r_[np.zeros(half), np.ones(len(t) - half)]
    assert max(structure(t, en, v, stretch).values()) < 1e-9
    gapped = t.copy()
    gapped[half:] += 5.0
    assert max(structure(gapped, en, v).values()) < 1e-9
    assert structure(t[:MIN_PAIRS], en[:MIN_PAIRS], v[:MIN_PAIRS]) == {}, "too few pairs: no figure"


def fixes(seconds, error, h_acc=0.8, seed=0):
    t, en, v = series(seconds, error, seed=seed)
    out = []
    for ti, (e, n), (ve, vn) in zip(t, en, v):
        lat = LAT0 + n / 111_195.0
        lon = LON0 + e / (111_195.0 * math.cos(math.radians(LAT0)))
        out.append(GnssFix(int(1e6 + ti * 1e6), True, lat, lon, 500.0, vn, ve, h_acc, 0.1))
    return out


def test_the_sink_measures_what_the_fixes_carry_and_says_a_wander_past_the_model():
    """A receiver that wanders as a random walk of 0.4 m/sqrt(s) against a model of 0.1: past SAY_RATIO
    at 10 s and said so; one as exact as the model's white noise alone is not; a resent fix and one
    out of order change nothing."""
    walk = PositionWander()
    stream = fixes(600.0, lambda t, rng: np.cumsum(rng.normal(0.0, 0.4 / math.sqrt(HZ), (len(t), 2)), axis=0),
                   seed=4)
    for s in stream[:100] + [stream[99], stream[97]] + stream[100:]:     # resent, then out of order
        walk.on_sample(s)
    got = walk.measure()
    sigma, q = FilterConfig().gnss_pos_sigma_m, FilterConfig().q_pos_m
    assert got["fixes"] == len(stream) and got["q_pos_m"] == q and got["sigma_m"] == sigma
    assert ratio_at(got) > SAY_RATIO
    at = next(r for r in got["lags"] if r["lag_s"] == SAY_LAG_S)
    assert at["model_m"] == pytest.approx(model(sigma, q, SAY_LAG_S), abs=1e-3)
    assert at["wander_m"] == pytest.approx(0.4 * math.sqrt(SAY_LAG_S / 2.0), rel=0.3)
    assert "may be its own wander" in said(got)
    quiet = PositionWander()
    for s in fixes(600.0, lambda t, rng: rng.normal(0.0, 0.1, (len(t), 2))):
        quiet.on_sample(s)
    assert ratio_at(quiet.measure()) < 1.0 and "may be its own wander" not in said(quiet.measure())
    assert PositionWander().measure() is None and said(None) is None


def test_a_receiver_that_always_calls_itself_poor_is_modelled_as_the_monitor_takes_it():
    """A receiver that reports h_acc 12 m fix after fix (4.8 m of noise): the monitor caps a fix's noise
    at 1.5 times what the receiver usually reports (guard.core.aiding.receiver), here 7.2 m, over the
    fixed 10 floors (3.5 m) it caps it at before anything is heard, so it takes the 4.8 m; the sink's
    model of each fix is the monitor's, not the tighter one."""
    walk = PositionWander()
    for s in fixes(300.0, lambda t, rng: rng.normal(0.0, 0.1, (len(t), 2)), h_acc=12.0):
        walk.on_sample(s)
    f = FilterConfig()
    assert walk.measure()["sigma_m"] == pytest.approx(f.gnss_pos_acc_fraction * 12.0)
    assert f.gnss_pos_acc_fraction * 12.0 > 10 * f.gnss_pos_sigma_m, "the usual figure, not the fixed bound, decides"


def walking(seconds, q=0.4, seed=4):
    """Fixes of a receiver whose position walks at q m/sqrt(s) against its exact velocity."""
    return fixes(seconds, lambda t, rng: np.cumsum(rng.normal(0.0, q / math.sqrt(HZ), (len(t), 2)), axis=0),
                 seed=seed)


def live(stream):
    said_lines = []
    w = LivePositionWander(said_lines.append)
    for s in stream:
        w.on_sample(s)
    return w, said_lines


def test_guard_run_says_a_wandering_receiver_once_and_lets_go_and_a_quiet_one_never():
    w, lines = live(walking(900.0))
    assert len(lines) == 1 and lines[0].startswith("GNSS position wanders") and "guard tune" in lines[0], lines
    assert w.said_us - int(1e6) <= (LIVE_MIN_SPAN_S + LIVE_CHECK_S) * 1e6 and w.done and len(w.rows) == 0
    w, lines = live(fixes(1800.0, lambda t, rng: rng.normal(0.0, 0.1, (len(t), 2))))
    assert lines == [] and w.checked is not None and w.checked < 1.0
    held = w._array()[:, 0]
    assert held[-1] - held[0] <= LIVE_KEEP_S + LIVE_CHECK_S + 1.0, "the latest 10 minutes, no more"


@pytest.mark.parametrize("seed", [4, 5])
def test_a_receiver_further_than_any_tuned_walk_is_said_to_be_faulty_or_attacked(seed):
    """A position walking at 3 m/sqrt(s) against its own velocity (glitches of metres every second):
    further than the largest walk guard tune fits (Q_POS_MAX times the default, its position_walk's
    bound), so guard replay and guard run say a receiver fault or a spoof, not a model to tune. The
    0.4 m/sqrt(s) walk of the test above stays within what tune fits. A profile whose walk is already
    at tune's most has nothing further to fit: its line is the fault's past SAY_RATIO only (a walk of 5
    m/sqrt(s) against its 2)."""
    f = FilterConfig()
    for q in (0.05, f.q_pos_m, 0.5, 3.0):           # tunable is tune's own bound, whatever the profile
        assert position_walk((1.0, math.inf), q, f.q_pos_m)[1] == pytest.approx(q * tunable(q))
    walk = PositionWander()
    for s in walking(600.0, q=3.0, seed=seed):
        walk.on_sample(s)
    got = walk.measure()
    at = next(r for r in got["lags"] if r["lag_s"] == SAY_LAG_S)
    assert at["tunable_m"] == pytest.approx(model(f.gnss_pos_sigma_m, Q_POS_MAX * f.q_pos_m, SAY_LAG_S), abs=1e-3)
    assert beyond_tune(got) and "a fault or a spoof" in said(got) and "may be its own" not in said(got)
    usual = PositionWander()
    for s in walking(600.0, q=0.4, seed=seed):
        usual.on_sample(s)
    assert not beyond_tune(usual.measure()) and "may be its own wander" in said(usual.measure())
    w, lines = live(walking(900.0, q=3.0, seed=seed))
    assert len(lines) == 1 and "a receiver fault or a spoof" in lines[0] and "may be its own" not in lines[0], lines
    most = PositionWander(FilterConfig(q_pos_m=Q_POS_MAX * f.q_pos_m))
    for s in walking(600.0, q=5.0, seed=seed):         # 2.5 times that walk: past SAY_RATIO
        most.on_sample(s)
    got = most.measure()
    at = next(r for r in got["lags"] if r["lag_s"] == SAY_LAG_S)
    assert at["tunable_m"] == at["model_m"] and SAY_RATIO * at["model_m"] < at["wander_m"] and beyond_tune(got)
    scaled = dict(got, lags=[dict(r, wander_m=1.2 * r["model_m"]) for r in got["lags"]])
    assert not beyond_tune(scaled), "within SAY_RATIO of the model: nothing said, whatever tune may fit"


def test_its_figure_is_that_of_the_latest_ten_minutes_and_a_boot_loop_holds_no_more():
    """Quiet for 15 minutes, then a walk of 0.12 m/sqrt(s) (under the line): the last check's ratio is
    the offline one of the fixes of the ten minutes before it. Then 60 reboots 20 s apart, each clock
    starting again: at most LIVE_SEGMENTS stretches held, and nothing said of the quiet ones."""
    def error(t, rng):
        walk = np.cumsum(rng.normal(0.0, 0.12 / math.sqrt(HZ), (len(t), 2)) * (t >= 900.0)[:, None], axis=0)
        return walk + rng.normal(0.0, 0.05, (len(t), 2))
    stream = fixes(1500.0, error)
    w, lines = live(stream)
    assert lines == []
    latest = PositionWander()
    for s in stream:
        if w.checked_us - LIVE_KEEP_S * 1e6 <= s.t_us <= w.checked_us:
            latest.on_sample(s)
    assert w.checked == pytest.approx(ratio_at(latest.measure()), rel=1e-9)
    whole = PositionWander()
    for s in stream:
        whole.on_sample(s)
    assert abs(w.checked - ratio_at(whole.measure())) > 0.05
    boot = LivePositionWander(lines.append)
    for k in range(60):
        for s in fixes(20.0, lambda t, rng: rng.normal(0.0, 0.05, (len(t), 2)), seed=k):
            boot.on_sample(s)
        assert len(np.unique(boot._array()[:, 5])) <= LIVE_SEGMENTS
    assert len(boot.sigma) <= LIVE_SEGMENTS * 20 * HZ and lines == []
