"""An IMU noisier than the tests take (guard.core.aiding.noisecap): said once, as a WARNING naming the
sensor and the factor, after SAY_S over the cap; not for a vibration within it, nor for a jolt."""

import pytest

from guard.core.aiding.imu import NOISE_CAP
from guard.core.aiding.noisecap import SAY_S, NoiseCap
from guard.core.monitor import MonitorConfig
from guard.model.events import Notice
from unit.synthetic import drive, of, run

AIR = MonitorConfig(declination_deg=0.0, vehicle="air")


def said(events):
    return [n.text for n in of(events, Notice) if n.level == "warning" and " times " in n.text and "noise reads" in n.text]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_accelerometers_vibrating_past_the_cap_are_said_once_with_the_factor(seed):
    """3 m/s^2 of white vibration at 50 Hz, 20 floors of 0.15: said once, the accelerometers named,
    its factor read within a fifth; the model's vibration (0.5, within the cap) says nothing."""
    _, events = run(drive(60.0, yaw=0.4, seed=seed, vibration=lambda t: 3.0), AIR)
    lines = said(events)
    assert len(lines) == 1 and lines[0].startswith("the accelerometers' noise reads"), lines
    factor = float(lines[0].split(", ")[1].split(" times")[0])
    assert 16 <= factor <= 24, lines
    _, events = run(drive(60.0, yaw=0.4, seed=seed, vibration=lambda t: 0.5), AIR)
    assert said(events) == []


def test_a_jolt_shorter_than_the_time_it_takes_is_not_said():
    """SAY_S is counted in all over the run, fusion by fusion: a gap is not time over it, nor is another
    sensor's; what was counted before the gap is kept."""
    cap = NoiseCap(NOISE_CAP)
    floors = (0.15, 0.15, 0.01)
    t, out = 0, []
    for k in range(int(SAY_S * 50) - 5):                # just under SAY_S at 50 Hz over the cap
        t += 20_000
        out += cap.step(t, [2.0, 0.1, 0.001], floors)
    t += 60_000_000                                     # a gap is not time over it
    out += cap.step(t, [2.0, 0.1, 0.001], floors)
    assert out == []
    for k in range(10):
        t += 20_000
        out += cap.step(t, [0.1, 0.1, 0.5], floors)     # the gyro over its cap: its own clock
    assert out == []
    for k in range(10):
        t += 20_000
        out += cap.step(t, [2.0, 0.1, 0.001], floors)
    assert len(out) == 1 and "accelerometers'" in out[0].text and "13 times accel_sigma_mps2" in out[0].text
