"""`guard replay` says how far the receiver's position wanders against its own velocity, against what
guard's model of it allows (guard.runtime.position_wander): a simulated receiver whose slow error
comes and goes within 20 s (a Gauss-Markov error of 2 m) is said to be past it, its position alarms
perhaps its own; the simulator's usual receiver is not; and a profile whose random walk covers it
(filter.q_pos_m, as guard tune fits it) brings the figure back within the model."""

import dataclasses
import json
import subprocess
import sys

import pytest

from conftest import ROOT
from guard.runtime.position_wander import SAY_LAG_S, SAY_RATIO, ratio_at
from guard_sim import scenario as scn
from guard_sim.run import run

LINE = "the receiver's position against its own velocity"


def replayed(tmp_path, name: str, config: str = "", **noise) -> tuple[dict, str]:
    base = scn.load("clean")
    sc = dataclasses.replace(base, duration_s=150.0, noise=dataclasses.replace(base.noise, **noise))
    log = tmp_path / f"{name}.tlog"
    if not log.exists():
        run(sc, 5, tlog=str(log))
    (tmp_path / "guard.toml").write_text(config)
    got = subprocess.run([sys.executable, "-m", "guard", "replay", str(log), "--report", str(tmp_path / f"{name}.json"),
                          "--config", str(tmp_path / "guard.toml")],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert got.returncode == 0, got.stderr
    line = next((x.strip() for x in got.stdout.splitlines() if LINE in x), "")
    return json.loads((tmp_path / f"{name}.json").read_text())["position_wander"], line


def test_a_receiver_that_wanders_past_the_model_is_said_and_a_usual_one_is_not(tmp_path):
    usual, line = replayed(tmp_path, "usual")
    assert ratio_at(usual) < SAY_RATIO and line.startswith(LINE) and "may be its own wander" not in line, line
    wandering, line = replayed(tmp_path, "wandering", gnss_pos_markov_m=2.0, gnss_pos_markov_tau_s=20.0)
    assert ratio_at(wandering) > 2.0 and "may be its own wander" in line and "filter.q_pos_m" in line, line
    at = next(r for r in wandering["lags"] if r["lag_s"] == SAY_LAG_S)
    assert f"{at['wander_m']:.2f} m over {SAY_LAG_S:g} s" in line
    covered, line = replayed(tmp_path, "wandering", "[filter]\nq_pos_m = 0.6\n")
    assert ratio_at(covered) < SAY_RATIO < ratio_at(wandering) and "may be its own wander" not in line, line
    assert covered["lags"] and [r["wander_m"] for r in covered["lags"]] == \
        pytest.approx([r["wander_m"] for r in wandering["lags"]]), "the same fixes, another model"


def test_the_tool_measures_each_log_and_the_totals_and_names_a_missing_one(shared, tmp_path):
    folder = shared / "data" / "ardupilot-sitl"
    if not folder.is_dir():
        pytest.skip(f"{folder} is not here (the shared data folder sits beside the project)")
    tool = [sys.executable, str(ROOT / "tools" / "receiver_wander.py")]
    got = subprocess.run([*tool, str(folder), "--json", str(tmp_path / "out.json")],
                         capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr
    results = json.loads((tmp_path / "out.json").read_text())
    assert len(results) == 2 and all(r["lags"] and ratio_at(r) < 1.0 for r in results), results
    assert got.stdout.count("wander/model (m): 1s") == 2 and "at 10 s: 2 logs" in got.stdout, got.stdout
    assert "past what the largest walk guard tune fits allows at 10 s (a fault or a spoof, not a receiver's usual " \
        "wander): 0 logs" in got.stdout, got.stdout
    got = subprocess.run([*tool, str(tmp_path / "absent.bin")], capture_output=True, text=True, timeout=60)
    assert got.returncode == 1 and got.stderr.strip() == f"guard: {tmp_path / 'absent.bin'}: no such file or folder"
