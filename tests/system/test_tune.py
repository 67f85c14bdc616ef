"""guard tune on a vehicle the defaults do not fit: a receiver 0.2 s late, which in turns reads as a
GNSS velocity attack, on wheels that slip as a car's. Tuned on two clean drives, the profile is quiet
on a third, held out, and the held-out drive's attack is still caught at once."""

import dataclasses
import subprocess
import sys
import tomllib

import pytest

from guard.config import Config, parse
from guard.runtime.replay import replay
from guard.runtime.tune import tune
from guard_sim import scenario as scn
from guard_sim.run import run
from guard_sim.scenario import Attack

STEP_AT_S = 80.0
SLIP = 0.01


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    work = tmp_path_factory.mktemp("tune")
    base = scn.load("clean")
    late = dataclasses.replace(base, duration_s=110.0, noise=dataclasses.replace(base.noise, gnss_delay_s=0.2),
                               route=dataclasses.replace(base.route, sideslip_rad_per_mps2=SLIP, max_yaw_jerk_radps3=2.0))
    paths = {}
    for seed in (1, 2, 3):
        paths[seed] = str(work / f"clean{seed}.tlog")
        run(late, seed, tlog=paths[seed])
    paths["attack"] = str(work / "attack3.tlog")
    truth = run(dataclasses.replace(late, attacks=(Attack("step", "gnss_pos", "east", 5.0, STEP_AT_S),)), 3,
                tlog=paths["attack"])
    paths["k0"] = truth["attacks"][0]["start_gnss_index"]
    return paths


def test_tuned_on_clean_drives_the_held_out_one_is_quiet_and_its_attack_caught(drives):
    held_out = replay(drives[3])
    assert held_out["alarms"], "the control: the defaults false-alarm on this vehicle"
    profile, cfg = tune([drives[1], drives[2]], Config(), say=lambda line: None)
    assert profile["filter"]["gnss_delay_s"] == pytest.approx(0.2)
    assert profile["filter"]["slip_rad_per_mps2"] == pytest.approx(SLIP, abs=0.004)
    assert "monitor" not in profile, "an IMU whose errors are white keeps its fusion rate"
    assert replay(drives[3], cfg)["alarms"] == []
    alarms = replay(drives["attack"], cfg)["alarms"]
    assert alarms and alarms[0]["sensor"] == "gnss_pos" and 0 <= alarms[0]["gnss_index"] - drives["k0"] <= 1, alarms[:2]
    # the profile is a config guard reads back as is
    text = "[filter]\n" + "".join(f"{k} = {v!r}\n" for k, v in profile["filter"].items())
    assert parse(tomllib.loads(text), "profile").monitor.filter.gnss_delay_s == pytest.approx(0.2)


def test_the_cli_writes_a_profile_and_names_a_missing_log(drives, tmp_path):
    out = tmp_path / "vehicle.toml"
    p = subprocess.run([sys.executable, "-m", "guard", "tune", drives[1], "--out", str(out)],
                       capture_output=True, text=True, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "gnss_delay_s" in out.read_text() and "largest statistic/threshold" in p.stdout
    p = subprocess.run([sys.executable, "-m", "guard", "tune", str(tmp_path / "absent.bin")],
                       capture_output=True, text=True, cwd=tmp_path)
    assert p.returncode == 1 and p.stderr.strip() == f"guard: error: {tmp_path / 'absent.bin'}: no such file"


# -- the IMU's fusion rate -------------------------------------------------------------------------------

WANDER_ATTACKS = {"gyro": Attack("bias", "gyro", "z", 0.05, STEP_AT_S), "mag": Attack("bias", "mag", "x", 0.05, STEP_AT_S),
                  "gnss": Attack("step", "gnss_pos", "east", 5.0, STEP_AT_S)}


@pytest.fixture(scope="module")
def wandering(tmp_path_factory):
    """A car whose compass wanders by 1.5 degrees over 0.1 s (a motor's or a wire's field): three clean
    drives and the third with each attack."""
    work = tmp_path_factory.mktemp("wander")
    base = scn.load("clean")
    sc = dataclasses.replace(base, duration_s=120.0,
                             noise=dataclasses.replace(base.noise, mag_wander_deg=1.5, mag_wander_tau_s=0.1))
    paths = {seed: str(work / f"clean{seed}.tlog") for seed in (1, 2, 3)}
    for seed, path in paths.items():
        run(sc, seed, tlog=path)
    for name, attack in WANDER_ATTACKS.items():
        paths[name] = str(work / f"{name}.tlog")
        run(dataclasses.replace(sc, attacks=(attack,)), 3, tlog=paths[name])
    return paths


def test_a_compass_that_wanders_faster_than_the_fusion_is_fused_slower_and_its_attacks_still_caught(wandering):
    """Fused at 50 Hz, the compass's wander is counted as fifty independent errors a second and the
    defaults alarm on the held-out drive; tune finds the rate at which it fits the model, 10 Hz,
    without blunting the compass's noise floor, and the held-out drive is quiet while a gyro bias, a
    magnetometer bias and a GNSS step are each caught within seconds."""
    assert replay(wandering[3])["alarms"], "the control: the defaults false-alarm on this compass"
    said: list[str] = []
    profile, cfg = tune([wandering[1], wandering[2]], Config(), say=said.append)
    assert profile["monitor"] == {"imu_fusion_hz": 10.0}, said
    assert any("caught later" in line for line in said), said
    assert profile["filter"].get("heading_sigma_rad", 0.03) < 0.06, "the floor is not blunted to hide the wander"
    assert replay(wandering[3], cfg)["alarms"] == []
    for name, sensors in (("gyro", {"gyro", "mag"}), ("mag", {"mag"}), ("gnss", {"gnss_pos"})):
        alarms = [a for a in replay(wandering[name], cfg)["alarms"] if a["time_usec"] >= STEP_AT_S * 1e6]
        assert alarms and alarms[0]["sensor"] in sensors, (name, alarms[:2])
        assert alarms[0]["time_usec"] / 1e6 - STEP_AT_S <= 5.0, (name, alarms[0])
