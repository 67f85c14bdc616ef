"""tools/imu_gnss_agreement.py and guard replay's line (guard.runtime.agreement): the levelled
accelerometers against the GNSS velocity's change, outside any filter. A simulated drive agrees within
the receiver's noise; the same drive with a constant accelerometer bias disagrees by that bias at
every window length, while its Allan deviation (what moves from window to window) stays small;
ArduPilot's SITL copter agrees; bad input is named."""

import dataclasses
import importlib.util
import json
import subprocess
import sys

import pytest

from conftest import ROOT
from guard.runtime.agreement import WANDER_SAY_MPS2, said
from guard_sim import scenario as scn
from guard_sim.run import run

TOOL = ROOT / "tools" / "imu_gnss_agreement.py"
BIAS = 0.5


def load():
    spec = importlib.util.spec_from_file_location("imu_gnss_agreement", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    work = tmp_path_factory.mktemp("agree")
    base = dataclasses.replace(scn.load("clean"), duration_s=120.0)
    paths = {}
    for seed in (1, 2):
        paths["clean", seed] = str(work / f"clean{seed}.tlog")
        run(base, seed, tlog=paths["clean", seed])
        paths["bias", seed] = str(work / f"bias{seed}.tlog")
        run(dataclasses.replace(base, attacks=(scn.Attack("bias", "accel", "x", BIAS, 1.0),)), seed,
            tlog=paths["bias", seed])
    return paths


@pytest.mark.parametrize("seed", [1, 2])
def test_a_constant_bias_is_its_size_at_every_window_and_does_not_move_between_windows(drives, seed):
    """The simulator's IMU has a small bias of its own (the clean drive's figure at long windows): the
    attack's adds to it as vectors, so the biased drive reads 0.5 m/s^2 give or take that."""
    tool = load()
    clean = {r["window_s"]: r for r in tool.measure(drives["clean", seed])["rows"]}
    biased = {r["window_s"]: r for r in tool.measure(drives["bias", seed])["rows"]}
    for w in (2.0, 4.0, 8.0):
        assert clean[w]["windows"] >= 10 and biased[w]["windows"] >= 10
        assert clean[w]["rms_mps2"] < 0.15, (w, clean[w])
        assert abs(biased[w]["rms_mps2"] - BIAS) <= clean[w]["rms_mps2"] + 0.05, (w, biased[w], clean[w])
    for w in (4.0, 8.0):
        # a constant error: what changes between windows is the receiver's noise, not the bias
        assert biased[w]["allan_mps2"] < 0.25 * biased[w]["rms_mps2"], (w, biased[w])
    # the receiver's velocity noise over short windows falls as they lengthen
    assert clean[0.4]["rms_mps2"] > clean[8.0]["rms_mps2"]
    assert clean[0.4]["allan_mps2"] > 2 * clean[8.0]["allan_mps2"]


def test_ardupilot_sitl_copter_agrees_within_a_tenth(shared):
    path = shared / "data" / "ardupilot-sitl" / "copter_clean_straight.tlog"
    if not path.exists():
        pytest.skip(f"{path} is not here (the shared data folder sits beside the project)")
    result = load().measure(str(path))
    assert all(r["windows"] > 20 and r["rms_mps2"] < 0.1 for r in result["rows"]), result


def test_bad_input_is_named_and_a_missing_file_is_an_error(drives, tmp_path):
    notes = tmp_path / "notes.bin"
    notes.write_text("not a log")
    got = subprocess.run([sys.executable, str(TOOL), drives["clean", 1], str(notes), "--windows", "1", "8",
                          "--jobs", "2"], capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr
    assert f"{notes}: skipped" in got.stdout and "Traceback" not in got.stderr
    assert "Allan dev." in got.stdout and "    8.0 s" in got.stdout
    got = subprocess.run([sys.executable, str(TOOL), str(tmp_path / "absent.bin")], capture_output=True, text=True,
                         timeout=60)
    assert got.returncode == 2 and f"{tmp_path / 'absent.bin'}: no such file" in got.stderr
    assert "Traceback" not in got.stderr


def test_guard_replay_says_the_wander_and_what_it_means_only_where_it_is_large(drives, tmp_path):
    report = tmp_path / "report.json"
    got = subprocess.run([sys.executable, "-m", "guard", "replay", drives["clean", 1], "--report", str(report)],
                         capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr
    rows = json.loads(report.read_text())["accelerometer_wander"]
    at8 = next(r for r in rows if r["window_s"] == 8.0)
    assert f"they wander {at8['allan_mps2']:.2f} m/s^2 over 8 s" in got.stdout
    assert "rarely tells one apart" not in got.stdout
    row = {"window_s": 8.0, "windows": 20, "allan_mps2": 2 * WANDER_SAY_MPS2}
    assert "rarely tells one apart" in said([row])
    assert "rarely tells one apart" not in said([{**row, "allan_mps2": WANDER_SAY_MPS2 / 2}])
    assert said([{**row, "allan_mps2": None}]) is None and said(None) is None
