"""PX4's IMU stream: HIGHRES_IMU in place of ArduPilot's RAW_IMU.

PX4 streams no RAW_IMU; its onboard link (a companion computer on TELEM2) sends HIGHRES_IMU at 50 Hz,
in SI floats. The simulator sends the same run either way (`guard sim --autopilot px4`), the same
numbers in both, so a replay of the two tlogs must give the same alarms at the same samples: the
attacks on the GNSS, the gyro and the accelerometers, over several seeds.
"""

import dataclasses
import struct

import pytest

from guard.runtime.replay import replay
from guard_sim import scenario as scn
from guard_sim.mavout import TLOG_EPOCH_US, Encoder
from guard_sim.run import Simulation, run


def alarms(report: dict) -> list[tuple]:
    return [(a["sensor"], a.get("channel"), a.get("gnss_index"), a.get("t_us")) for a in report["alarms"]]


@pytest.mark.parametrize("name, seed", [("paper", 1), ("paper", 4), ("gyro_bias", 2), ("accel_bias", 3)])
def test_a_px4_stream_gives_the_alarms_of_the_same_run_as_ardupilot(tmp_path, name, seed):
    sc = scn.load(name)
    if name != "paper":
        sc = dataclasses.replace(sc, duration_s=45.0)       # the attack from 30 s on
    reports = {}
    for autopilot in ("ardupilot", "px4"):
        path = tmp_path / f"{autopilot}.tlog"
        run(sc, seed, tlog=str(path), autopilot=autopilot)
        reports[autopilot] = replay(str(path))
    ap, px4 = reports["ardupilot"], reports["px4"]
    assert "HIGHRES_IMU" in px4["messages"] and "RAW_IMU" not in px4["messages"]
    assert px4["samples"] == ap["samples"]
    assert alarms(ap), f"{name} seed {seed}: the attack was not caught from RAW_IMU either"
    assert alarms(px4) == alarms(ap)
    assert px4["peak_ratio"] == pytest.approx(ap["peak_ratio"], abs=0.002)


def test_a_tlog_with_both_imu_streams_reads_the_first_and_says_so(tmp_path):
    """A vehicle that sends RAW_IMU and HIGHRES_IMU (a custom stream set): each motion once, not twice."""
    sc = dataclasses.replace(scn.load("paper"), duration_s=20.0)
    both, alone = tmp_path / "both.tlog", tmp_path / "alone.tlog"
    run(sc, 1, tlog=str(alone))
    sim, px4 = Simulation(sc, 1), Encoder("px4")
    with open(both, "wb") as f:
        for t_us, msgs in sim.ticks():
            for msg in msgs:
                f.write(struct.pack(">Q", TLOG_EPOCH_US + t_us) + sim.encoder.pack(msg))
                if msg.get_type() == "RAW_IMU":     # the same reading again, as PX4 would send it
                    f.write(struct.pack(">Q", TLOG_EPOCH_US + t_us) + px4.pack(msg))
    got, want = replay(str(both)), replay(str(alone))
    assert got["messages"]["HIGHRES_IMU"] == got["messages"]["RAW_IMU"] > 0
    assert got["skipped"]["imu_other_stream"] == got["messages"]["HIGHRES_IMU"]
    assert got["samples"] == want["samples"]
    assert any("HIGHRES_IMU is sent too" in n and "RAW_IMU" in n for n in got["notes"]), got["notes"]
    assert alarms(got) == alarms(want) == []
