"""What a tuned vehicle's receiver is believed to usually be (guard.core.aiding.receiver, `UsualWorst`,
`gnss_h_acc_usual_max_m`, `gnss_vel_acc_usual_max_mps`): a spoofer who raises the receiver's claimed
error slowly, then moves it, blunts the tests of an untuned vehicle and not of a tuned one."""

import dataclasses
import statistics

import pytest
from hypothesis import given
from hypothesis import strategies as st

from guard.core.aiding.receiver import LEVEL_FACTOR, LEVEL_WINDOW_S, TimedMedian, UsualWorst, bound
from guard.core.ekf import FilterConfig
from guard.core.monitor import MonitorConfig
from guard.model.events import Alarm, Notice
from guard.model.samples import GnssFix
from guard.runtime.tune import Figures, usual_max
from unit.synthetic import T0_US, drive, of, run

SPOOF_AT_S = 200.0
BEYOND = "more than guard tune believes of this vehicle"


def claim(t: float) -> float:
    """The receiver's claimed velocity accuracy: 0.1 m/s, creeping up to 3 m/s from 30 s to 150 s."""
    return 0.1 if t < 30.0 else min(3.0, 0.1 + 2.9 * (t - 30.0) / 120.0)


def creeping(seed: int) -> list:
    """A receiver good to 0.1 m/s whose claim creeps up (claim) while nothing else moves, then at
    SPOOF_AT_S its velocity is pulled 2 m/s north."""
    samples = drive(SPOOF_AT_S + 20.0, seed=seed,
                    vel_offset=lambda t: (0.0, 2.0 if t >= SPOOF_AT_S else 0.0))
    return [dataclasses.replace(s, vel_acc_mps=claim((s.t_us - T0_US) / 1e6)) if isinstance(s, GnssFix) else s
            for s in samples]


def first_alarm_after_spoof(events):
    onset = T0_US + int(SPOOF_AT_S * 1e6)
    alarms = [a for a in of(events, Alarm) if a.t_us >= onset]
    return (alarms[0], onset) if alarms else (None, onset)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_slow_claim_then_a_spoof_is_caught_on_a_tuned_vehicle_and_missed_on_an_untuned_one(seed):
    samples = creeping(seed)
    # untuned: the bound follows the claim up (1.5 times its usual median, up to 50 floors), the spoof
    # sits inside it
    mon, events = run(samples)
    alarm, onset = first_alarm_after_spoof(events)
    assert alarm is None, alarm                     # not in the 20 s after the spoof
    assert mon.gnss_aid.cap_vel() > 1.5
    # tuned: this receiver's usual vel_acc believed up to 0.2 m/s; the cap stays the fixed one
    tuned = MonitorConfig(declination_deg=0.0, filter=FilterConfig(gnss_vel_acc_usual_max_mps=0.2))
    mon, events = run(samples, tuned)
    alarm, onset = first_alarm_after_spoof(events)
    assert alarm is not None and alarm.sensor.startswith("gnss") and alarm.t_us - onset < 2_000_000, alarm
    assert mon.gnss_aid.cap_vel() == pytest.approx(0.6)
    told = [n for n in of(events, Notice) if BEYOND in n.text]
    assert len(told) == 1 and told[0].level == "warning" and told[0].t_us < onset, [n.text for n in of(events, Notice)]
    assert "gnss_vel_acc_usual_max_mps 0.2" in told[0].text
    assert not [a for a in of(events, Alarm) if a.t_us < onset], "the creeping claim alone raises no alarm"


def test_a_tuned_receiver_within_what_it_usually_says_is_neither_told_nor_capped():
    """A receiver poor all along (1.2 m/s, reported) on a vehicle tuned to it (usual up to 2.4 m/s): as
    untuned, it is taken at its word, quiet, and nothing is said of the tuned ceiling."""
    samples = drive(150.0, seed=4, vel_noise=1.2, vel_acc=1.2)
    tuned = MonitorConfig(declination_deg=0.0, filter=FilterConfig(gnss_vel_acc_usual_max_mps=2.4))
    mon, events = run(samples, tuned)
    assert not of(events, Alarm)
    assert not [n for n in of(events, Notice) if BEYOND in n.text]
    assert mon.gnss_aid.cap_vel() == pytest.approx(LEVEL_FACTOR * mon.gnss_aid.level.vel_acc)


def test_the_bound_takes_the_usual_figure_up_to_the_tuned_most():
    assert bound(0.06, 0.6, 1.0) == pytest.approx(1.5)
    assert bound(0.06, 0.6, 1.0, usual_max=0.8) == pytest.approx(1.2)
    assert bound(0.06, 0.6, 1.0, usual_max=0.2) == pytest.approx(0.6)       # never under the fixed bound
    assert bound(0.06, 0.6, 10.0, usual_max=20.0) == pytest.approx(3.0)     # nor over 50 floors
    assert bound(0.06, 0.6, None, usual_max=0.2) == pytest.approx(0.6)


def fix(t_s: float, h: float | None, v: float | None, ok: bool = True) -> GnssFix:
    return GnssFix(T0_US + int(t_s * 1e6), ok, 47.0, 8.0, 400.0, 0.0, 0.0, h, v)


def test_the_worst_usual_figure_leaves_out_a_receiver_settling_after_a_start_a_reboot_or_a_gap():
    """A receiver that starts at 5 m and settles to 1 m in 30 s, then reports 1 m (0.2 m/s) with a
    two-minute spell at 1.6 m (0.4 m/s): the worst usual figure is the spell's median, not the
    settling. After a reboot (time back, the new log starting later than the first did) and after a
    200 s gap, the receiver settles from 5 m again: not counted. A second log that is worse once
    settled counts."""
    def log(w, t0, t1, figures):
        for i in range(int(t0 * 10), int(t1 * 10)):
            w.hear(fix(i / 10, *figures(i / 10 - t0)))

    def settling_then(h, v):
        return lambda t: (5.0 - 4.0 * t / 30.0, 0.8) if t < 30.0 else (h, v)

    w = UsualWorst()
    log(w, 20.0, 380.0, lambda t: (1.6, 0.4) if 180.0 <= t < 300.0 else settling_then(1.0, 0.2)(t))
    assert w.worst() == (pytest.approx(1.6), pytest.approx(0.4))
    log(w, 30.0, 230.0, settling_then(1.0, 0.2))          # a reboot: time back, later than the first start
    log(w, 430.0, 630.0, settling_then(1.0, 0.2))         # a gap of 200 s
    assert w.worst() == (pytest.approx(1.6), pytest.approx(0.4))
    log(w, 0.0, 200.0, settling_then(2.1, 0.5))           # a reboot into a poorer sky
    assert w.worst() == (pytest.approx(2.1), pytest.approx(0.5))


def test_a_tuned_receiver_settling_after_power_on_is_not_said_to_be_beyond_its_most():
    """A tuned receiver (usual h_acc up to 2 m, vel_acc 0.4 m/s) that settles from 4.5 m and 0.8 m/s
    to 1 m and 0.2 m/s over its first 40 s: nothing said of its tuned most (its first fixes are no
    usual figure, as they are not to guard tune); the same receiver settling to 3 m and 0.6 m/s is
    said to be beyond it, once, after its figures have settled."""
    def settling(h, v):
        return lambda t: (4.5 + (h - 4.5) * min(t / 40.0, 1.0), 0.8 + (v - 0.8) * min(t / 40.0, 1.0))

    tuned = MonitorConfig(declination_deg=0.0, filter=FilterConfig(gnss_h_acc_usual_max_m=2.0,
                                                                   gnss_vel_acc_usual_max_mps=0.4))
    for (h, v), said in (((1.0, 0.2), 0), ((3.0, 0.6), 1)):
        figures = settling(h, v)
        samples = [dataclasses.replace(s, h_acc_m=figures((s.t_us - T0_US) / 1e6)[0],
                                       vel_acc_mps=figures((s.t_us - T0_US) / 1e6)[1])
                   if isinstance(s, GnssFix) else s for s in drive(200.0, seed=6)]
        _, events = run(samples, tuned)
        told = [n for n in of(events, Notice) if BEYOND in n.text]
        assert len(told) == said, [n.text for n in told]
        assert all(n.t_us - T0_US >= 60e6 for n in told), told


def test_a_short_log_gives_its_median_and_a_silent_receiver_nothing():
    short = UsualWorst()
    for i in range(200):                # 20 s: shorter than half the window
        short.hear(fix(i / 10, 0.7, 0.15))
    short.hear(fix(20.0, 9.0, 9.0, ok=False))      # a lost fix is no figure
    assert short.worst() == (pytest.approx(0.7), pytest.approx(0.15))
    silent = UsualWorst()
    for i in range(int(LEVEL_WINDOW_S * 10)):
        silent.hear(fix(i / 10, None, None))
    assert silent.worst() == (None, None)
    # guard tune's keys: twice the worst, each only where some log reported it
    figs = [Figures(), Figures(), Figures()]
    figs[0].worst, figs[1].worst, figs[2].worst = short, silent, UsualWorst()
    for i in range(200):
        figs[2].on_sample(fix(i / 10, 1.1, None))
    assert usual_max(figs) == {"gnss_h_acc_usual_max_m": 2.2, "gnss_vel_acc_usual_max_mps": 0.3}
    assert usual_max([figs[1]]) == {}


@given(st.lists(st.tuples(st.integers(-1, 10).map(lambda s: s * 1_000_000),
                          st.one_of(st.floats(0.01, 10.0), st.sampled_from([None, 0.0]))),
                min_size=1, max_size=300))
def test_the_kept_median_is_the_window_s_median(heard):
    """TimedMedian keeps its window sorted as values come and go: at every step its median is
    statistics.median of the values heard over the window, the window started over when time goes back."""
    window = TimedMedian(30.0)
    naive: list[tuple[int, float]] = []
    t = 0
    for dt, value in heard:
        t += dt
        if naive and t < naive[-1][0]:
            naive = []
        if value:
            naive.append((t, value))
        naive = [(u, v) for u, v in naive if u >= t - 30e6]
        window.hear(t, value)
        assert window.median() == (statistics.median(v for _, v in naive) if naive else None)
