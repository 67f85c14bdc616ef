"""A log's clock against its receiver's motion (guard.sources.clock): found where the vehicle goes
far, left alone where it hovers or its fixes jump."""

import math

import numpy as np
import pymap3d
import pytest

from guard.sources.clock import epoch_clock, epoch_rate, gnss_time_clock, motion_clock, motion_rate

LAT0, LON0 = 43.0, -2.6


def track(speed, rate, seconds=300.0, hz=5.0, wander=0.5, seed=0, turn=0.02):
    """Fixes of a vehicle at `speed`, turning slowly, stamped by a clock `rate` times too slow; its
    position wanders (a random walk of `wander` m over a minute) and its velocity is noisy."""
    rng = np.random.default_rng(seed)
    out, e, n, walk = [], 0.0, 0.0, np.zeros(2)
    for k in range(int(seconds * hz)):
        t = k / hz
        heading = turn * t
        ve, vn = speed * math.cos(heading), speed * math.sin(heading)
        e, n = e + ve / hz, n + vn / hz
        walk += rng.normal(0.0, wander / math.sqrt(60 * hz), 2)
        lat, lon, _ = pymap3d.enu2geodetic(e + walk[0], n + walk[1], 0.0, LAT0, LON0, 0.0)
        out.append((round(1e6 * t / rate), float(lat), float(lon), vn + rng.normal(0, 0.1), ve + rng.normal(0, 0.1)))
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_slow_clock_on_a_vehicle_that_goes_far_is_found(seed):
    notes = []
    t0, rate = motion_clock(track(15.0, 1.085, seed=seed), notes)
    assert t0 == 0 and rate == pytest.approx(1.085, abs=0.005)
    assert len(notes) == 1 and " % slow against its receiver" in notes[0] and "scaled by 1.08" in notes[0], notes


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_good_clock_or_a_hovering_vehicle_is_left_as_logged(seed):
    notes = []
    assert motion_clock(track(15.0, 1.0, seed=seed), notes) is None and notes == []
    assert motion_rate(track(1.5, 1.085, seed=seed)) is None          # 15 m per stretch: never judged
    assert motion_clock(track(1.5, 1.085, seed=seed), notes) is None and notes == []


def test_a_track_whose_fixes_jump_is_not_a_clock():
    """A receiver that jumps by tens of metres (glitches): the stretches disagree, nothing is taken."""
    fixes = track(8.0, 1.0, seed=4)
    rng = np.random.default_rng(4)
    jumped = [(t, lat + (rng.normal(0, 3e-4) if k % 50 < 10 else 0.0), lon, vn, ve)
              for k, (t, lat, lon, vn, ve) in enumerate(fixes)]
    notes = []
    assert motion_clock(jumped, notes) is None and notes == []


def epochs(n, rate, period_ms=200.0, loop_ms=20.0, missed=0.02, seed=0):
    """Fix times of a receiver at period_ms on GPS time, read by an autopilot loop of loop_ms whose
    clock runs `rate` times too slow: each fix stamped at the first loop tick after it; a few missed."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        if rng.random() < missed:
            continue
        t_true = k * period_ms / 1e3
        t_log_ms = t_true * 1e3 / rate
        out.append(int(math.ceil(t_log_ms / loop_ms) * loop_ms * 1000))
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_slow_clock_is_found_by_its_receivers_epochs_where_the_vehicle_hovers(seed):
    """The Erle autopilot's GPS rows came 180 or 200 ms apart on its 20 ms loop, 184.6 ms on average:
    a 5 Hz receiver read by a clock 8.3 % slow."""
    notes = []
    t0, rate = epoch_clock(epochs(1500, 1.083, seed=seed), notes)
    assert rate == pytest.approx(1.083, abs=0.003) and "200 ms receiver" in notes[0], notes


@pytest.mark.parametrize("period_ms", [100.0, 200.0, 1000.0])
def test_a_receiver_read_by_a_good_clock_or_a_telemetry_stream_is_left_as_logged(period_ms):
    notes = []
    assert epoch_clock(epochs(1500, 1.0, period_ms=period_ms), notes) is None and notes == []
    rng = np.random.default_rng(5)              # a 1 Hz telemetry stream sampling a 5 Hz receiver
    scattered = np.cumsum(rng.choice([200_000, 400_000, 600_000, 800_000, 1_000_000], 1500))
    assert epoch_rate(scattered.tolist()) is None
    assert epoch_rate(epochs(100, 1.083)) is None                       # too few to judge
    assert epoch_clock(epochs(1500, 1.0, period_ms=1000.0 / 9), notes) is None     # a 9 Hz receiver is one


def gnss_times(rate, seconds=300.0, hz=5.0, stale=0.0, late=0.0, seed=0):
    """(boot s, GNSS s) of fixes of a receiver at `hz`, stamped by a clock `rate` times too slow on a
    20 ms loop; a share `stale` of them carries the GNSS time of the epoch before (its driver had not yet
    updated it), a share `late` is read up to 0.9 s late."""
    rng = np.random.default_rng(seed)
    boot, gps = [], []
    for k in range(int(seconds * hz)):
        t = k / hz
        b = math.ceil(t / rate / 0.02) * 0.02
        if rng.random() < late:
            b += rng.uniform(0.2, 0.9) / rate
        boot.append(b)
        gps.append(1_000_000.0 + t - (1.0 / hz if rng.random() < stale else 0.0))
    return boot, gps


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_slow_clock_is_found_by_the_gnss_time_past_fixes_whose_time_lags(seed):
    """The Erle copters' DataFlash logs: 9 to 23 % of their fixes carry a GNSS time an epoch behind
    (or were read late), which a line through all of them takes for jitter. Three quarters on a line
    are a clock: found, those left out counted."""
    for stale, late in ((0.15, 0.0), (0.1, 0.05), (0.2, 0.0)):
        notes = []
        t0, rate = gnss_time_clock(*gnss_times(1.083, stale=stale, late=late, seed=seed), notes)
        assert rate == pytest.approx(1.083, abs=5e-4), (stale, late)
        assert len(notes) == 1 and "8.3 % slow against the GNSS receiver's" in notes[0], notes
        left = int(notes[0].split("(")[1].split(" of its")[0])
        assert 0.5 * (stale + late) * 1500 < left < 1.5 * (stale + late) * 1500, notes


@pytest.mark.parametrize("seed", [1, 2])
def test_a_gnss_time_that_is_no_line_corrects_nothing(seed):
    """Too many strays (a third of the fixes), or a GNSS time that jumps by a minute, ahead or back, early,
    half-way or late in the log (a receiver restarting, or a spoofer moving its clock): said, left as
    logged, whether the clock keeps time or not. A clock that keeps time, its strays or not: nothing
    said."""
    notes = []
    assert gnss_time_clock(*gnss_times(1.083, stale=0.2, late=0.15, seed=seed), notes) is None
    assert len(notes) == 1 and "time stamps left as logged" in notes[0], notes
    for rate in (1.083, 1.0):       # a minute ahead or behind, from 10, 50 or 90 % of the log on
        for at, jump in ((0.1, 60.0), (0.5, 60.0), (0.9, 60.0), (0.9, -60.0), (0.1, -60.0)):
            boot, gps = gnss_times(rate, seed=seed)
            gps = [g + (jump if k > at * len(gps) else 0.0) for k, g in enumerate(gps)]
            notes = []
            assert gnss_time_clock(boot, gps, notes) is None and "left as logged" in notes[0], (rate, at, jump, notes)
    for stale in (0.0, 0.15):
        notes = []
        assert gnss_time_clock(*gnss_times(1.0, stale=stale, seed=seed), notes) is None and notes == [], notes
