"""What guard learns of the vehicle cannot be taught by a slow attack.

The compass offset b_psi is a state of the filter, learnt from the GNSS course and the turns; the IMU's
noise is measured from its own readings. A slow GNSS attack (a ramp, a coordinated spoof) bends the
course the filter sees long before its alarm, and a filter that learnt from it all along would take
part of the attack for a compass offset. guard learns only while every test is well under its
threshold (guard.core.judge.CALM_RATIO): these drives show the attack still caught, at most one GNSS
sample later than by a filter that learns throughout, and the offset at the alarm within a degree of the one learnt
before the attack began and nearer to it than that filter's. (The alarm's rewind then restores the
offset of the epoch before the attack's onset as well.) The vehicles have a compass 4 degrees off
(the learning has work to do), at a 1 Hz and a 5 Hz receiver (the harness's second noise family,
seeds 0 and 2).
"""

import dataclasses
import math

import pytest

from guard.config import parse
from guard.core import judge
from guard.core.ekf import BM
from guard.core.monitor import Monitor
from guard.model.events import Alarm, Estimate
from guard.sources.tlog import TlogReader
from guard_sim import scenario as scenarios
from guard_sim.run import run
from guard_sim.scenario import Attack

pytestmark = pytest.mark.slow

VEHICLES = {   # two of the harness's --vehicles draws, the compass turned 4 degrees
    0: dict(mag_offset_deg=4.0, gnss_vel_white_mps=0.2, gnss_vel_acc_reported=False, gnss_h_acc_reported=True,
            accel_scale=0.02, gyro_scale=-0.01, imu_yaw_mount_deg=1.5, gnss_hz=1.0, imu_hz=50.0),
    2: dict(mag_offset_deg=-4.0, gnss_vel_white_mps=0.1, gnss_vel_acc_reported=True, gnss_h_acc_reported=False,
            accel_scale=-0.02, gyro_scale=0.02, imu_yaw_mount_deg=-2.0, gnss_hz=5.0, imu_hz=100.0),
}
ATTACKS = {"ramp north 0.3 m/s": (Attack("ramp", "gnss_pos", "north", 0.3, 30.0), 90.0),
           "spoof east 0.05 m/s2": (Attack("spoof", "gnss_pos", "east", 0.05, 48.0), 120.0)}


def drive(tmp_path, name: str, seed: int):
    attack, duration = ATTACKS[name]
    car = VEHICLES[seed]
    rates = {k: car[k] for k in ("gnss_hz", "imu_hz")}
    noise = {k: v for k, v in car.items() if k not in rates}
    base = scenarios.load("clean")
    sc = dataclasses.replace(base, duration_s=duration, attacks=(attack,),
                             rates=dataclasses.replace(base.rates, **rates),
                             noise=dataclasses.replace(base.noise, **noise))
    tlog = tmp_path / f"{seed}-{name.split()[0]}.tlog"
    truth = run(sc, seed, tlog=str(tlog))
    return tlog, truth["attacks"][0]["start_gnss_index"]


def replay(tlog, k0: int, calm_ratio: float, monkeypatch):
    """(GNSS sample of the first alarm at or after k0, b_psi just before k0, b_psi just before it)."""
    monkeypatch.setattr(judge, "CALM_RATIO", calm_ratio)
    reader = TlogReader(str(tlog))
    monitor = Monitor(parse({}, "defaults").monitor, record_tests=False, date=reader.date)
    b_psi, first = {}, None
    for sample in reader.samples():
        for e in monitor.step(sample):
            if isinstance(e, Estimate):
                b_psi[e.gnss_index] = e.x[BM]
            elif isinstance(e, Alarm) and first is None:
                assert e.gnss_index >= k0, f"a false alarm before the attack: {e}"
                first = e.gnss_index
    reader.close()
    assert first is not None, "the attack was never caught"
    return first, math.degrees(b_psi[k0 - 1]), math.degrees(b_psi[first - 1])


@pytest.mark.parametrize("seed", sorted(VEHICLES))
@pytest.mark.parametrize("name", sorted(ATTACKS))
def test_a_slow_attack_cannot_teach_the_filter_its_compass_offset(tmp_path, monkeypatch, name, seed):
    tlog, k0 = drive(tmp_path, name, seed)
    k_guarded, before, at_alarm = replay(tlog, k0, judge.CALM_RATIO, monkeypatch)
    k_always, _, at_alarm_always = replay(tlog, k0, math.inf, monkeypatch)    # a filter that always learns
    # the offset was learnt before the attack (4 degrees, within the noise of its learning) ...
    assert abs(abs(before) - 4.0) < 0.5
    # ... and the attack moved it by less than a degree by its alarm, and by less than it moves the
    # offset of a filter that learns throughout (which the attack pushes on as long as it goes)
    moved, moved_always = abs(at_alarm - before), abs(at_alarm_always - before)
    assert moved < 1.0
    assert moved <= 0.9 * moved_always or moved_always < 0.1, (moved, moved_always)
    # holding the learning delays the alarm by at most one GNSS sample (measured: the same sample in three
    # of the four drives, one later in the ramp on the 1 Hz receiver since the wheels' slip model, 59
    # against 58: the held offset and the learning one part the filters' paths a little either way)
    assert k_guarded <= k_always + 1
