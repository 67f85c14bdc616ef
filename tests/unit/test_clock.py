"""A log's clock against its receiver's motion (guard.sources.clock): found where the vehicle goes
far, left alone where it hovers or its fixes jump."""

import math

import numpy as np
import pymap3d
import pytest

from guard.sources.clock import motion_clock, motion_rate

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
