"""A fix a receiver epoch off its own stamp (guard.core.aiding.stamp): a 5 Hz receiver's fixes sent at
2 Hz, as a QuadPlane's telemetry carried them, now and then a position paired with the next epoch's
stamp. Brought back, never alarmed; a step along the track is still caught, one fix later at most."""

import math

import numpy as np
import pymap3d
import pytest

from guard.core.aiding import stamp
from guard.core.aiding.stamp import FixStamps
from guard.core.monitor import Monitor
from guard.model.events import Alarm
from guard.model.samples import GnssFix
from guard.model.sensors import Sensor

LAT0, LON0, ALT0 = 47.397742, 8.545594, 488.0
EPOCH_S, SEND_S = 0.2, 0.5          # the receiver's epoch, the stream's interval
SPEED, TRACK = 20.0, math.radians(30.0)   # m/s; the track's direction from east
SLIPS = (24, 25 + 12, 62, 63 + 22, 130, 131 + 9)   # the messages whose position is an epoch off


def stream(seed, duration_s=80.0, slips=SLIPS, offset=None, every_fix=False):
    """The fixes as sent: each message the receiver's latest epoch, stamped with that epoch's time;
    a message in `slips` carries the position of the epoch after (even index) or before (odd) its
    stamp. offset(t) -> (de, dn) adds an attack. every_fix: every epoch sent (an unthinned stream)."""
    rng = np.random.default_rng(seed)
    ve, vn = SPEED * math.cos(TRACK), SPEED * math.sin(TRACK)
    out, k = [], 0
    step = EPOCH_S if every_fix else SEND_S
    while k * step <= duration_s:
        epoch = math.floor(round(k * step / EPOCH_S, 6)) * EPOCH_S
        at = epoch + (EPOCH_S if k % 2 == 0 else -EPOCH_S) * (k in slips)
        de, dn = offset(epoch) if offset else (0.0, 0.0)
        e, n = ve * at + de + rng.normal(0.0, 0.1), vn * at + dn + rng.normal(0.0, 0.1)
        lat, lon, _ = pymap3d.enu2geodetic(e, n, 0.0, LAT0, LON0, ALT0)
        out.append(GnssFix(1_000_000 + round(epoch * 1e6), True, float(lat), float(lon), ALT0,
                           vn + rng.normal(0.0, 0.1), ve + rng.normal(0.0, 0.1), 1.0, 0.2))
        k += 1
    return out


def run(fixes):
    m = Monitor(record_tests=False)
    events = [e for f in fixes for e in m.step(f)] + m.finish()
    return m, [e for e in events if isinstance(e, Alarm)]


@pytest.mark.parametrize("seed", range(4))
def test_fixes_an_epoch_off_their_stamps_are_brought_back_and_raise_no_alarm(seed):
    m, alarms = run(stream(seed))
    assert not alarms, alarms
    assert m.skipped["gnss_stamp_slipped"] == len(SLIPS)
    # the same stream without its slips: nothing brought back
    m, alarms = run(stream(seed, slips=()))
    assert not alarms and m.skipped["gnss_stamp_slipped"] == 0


def first_alarm(fixes):
    """The index of the fix at which the first GNSS position alarm came (None: none)."""
    _, alarms = run(fixes)
    at = [a.t_us for a in alarms if a.sensor is Sensor.GNSS_POS]
    return None if not at else [f.t_us for f in fixes].index(at[0])


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("size_m", [3.0, 4.0, 5.0])
def test_a_step_along_the_track_costs_one_fix_at_most_and_across_it_nothing(seed, size_m, monkeypatch):
    """A step along the track within MAX_SLIP_S of the speed is taken at its first fix as a slip; the
    second shows it. Against the same fixes with nothing brought back (MAX_SLIP_S 0)."""
    onset = 60.0
    ways = {"along": (math.cos(TRACK), math.sin(TRACK)), "across": (-math.sin(TRACK), math.cos(TRACK))}
    for name, (we, wn) in ways.items():
        fixes = stream(seed, slips=(), offset=lambda t: (size_m * we, size_m * wn) if t >= onset else (0.0, 0.0))
        with monkeypatch.context() as m:
            m.setattr(stamp, "MAX_SLIP_S", 0.0)
            without = first_alarm(fixes)
        with_ = first_alarm(fixes)
        if without is None:
            continue
        assert with_ is not None, (name, size_m)
        assert with_ <= without + (1 if name == "along" else 0), (name, size_m, with_, without)
        if size_m >= 4.0:           # over 8 sigma of the fix: by its second fix, whichever way
            assert with_ <= [f.t_us >= 1_000_000 + onset * 1e6 for f in fixes].index(True) + 1, (name, size_m)


def test_an_unthinned_stream_is_never_brought_back():
    """Every epoch sent (a DataFlash log's, the simulator's): its stamps are its fixes' own, and a
    fix off them is the tests' to judge."""
    m, alarms = run(stream(0, every_fix=True, slips=(120, 121 + 40, 300)))
    assert m.skipped["gnss_stamp_slipped"] == 0
    assert alarms, "a fix 4 m off its stamp on a stream with every fix in it is the tests' to judge"


def test_a_frozen_fix_and_a_fix_without_velocity_are_not_slips():
    stamps = FixStamps()
    t, en = 0, (0.0, 0.0)
    fixes = stream(0, duration_s=10.0, slips=())
    for f in fixes:
        e, n, _ = pymap3d.geodetic2enu(f.lat_deg, f.lon_deg, ALT0, LAT0, LON0, ALT0)
        en = stamps.check(f, (e, n), 0.4)
        t = f.t_us
    frozen = GnssFix(t + 500_000, True, fixes[-1].lat_deg, fixes[-1].lon_deg, ALT0,
                     fixes[-1].vel_n_mps, fixes[-1].vel_e_mps, 1.0, 0.2)
    assert stamps.check(frozen, en, 0.4) == en and stamps.brought_back == 0
    blind = GnssFix(t + 1_000_000, True, 0.0, 0.0, ALT0, None, None, 1.0, 0.2)
    assert stamps.check(blind, (1.0, 2.0), 0.4) == (1.0, 2.0) and stamps.brought_back == 0
