"""tools/compass_deviation.py: a compass's hard iron fitted against the gyro, per log."""

import dataclasses
import json
import subprocess
import sys

import pytest

from conftest import ROOT
from guard_sim import scenario as scn
from guard_sim.run import run


def tool(*args):
    return subprocess.run([sys.executable, str(ROOT / "tools" / "compass_deviation.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("iron", [(0.3, -0.2), (-0.1, 0.25)])
def test_a_simulated_hard_iron_is_recovered_and_none_where_there_is_none(tmp_path, iron):
    """Two minutes of the clean loop, its compass with a hard iron and without: the fit recovers the iron
    within 0.02 of the horizontal field and finds none on the clean compass, both shown by the turns."""
    base = scn.load("clean")
    for name, (dx, dy) in (("iron", iron), ("clean", (0.0, 0.0))):
        noise = dataclasses.replace(base.noise, mag_iron_x=dx, mag_iron_y=dy)
        run(dataclasses.replace(base, duration_s=120.0, noise=noise), 3, tlog=str(tmp_path / f"{name}.tlog"))
    got = tool(tmp_path, "--json", tmp_path / "out.json")
    assert got.returncode == 0, got.stderr
    by = {r["log"].rsplit("/", 1)[-1]: r for r in json.loads((tmp_path / "out.json").read_text())}
    found, clean = by["iron.tlog"], by["clean.tlog"]
    assert found["shown"] and abs(found["dx"] - iron[0]) < 0.02 and abs(found["dy"] - iron[1]) < 0.02, found
    assert found["scatter_deg"] < found["scatter_without_deg"] / 3
    assert clean["shown"] and abs(clean["dx"]) < 0.02 and abs(clean["dy"]) < 0.02, clean
    assert "iron.tlog: up to " in got.stdout and got.stdout.splitlines()[-1].startswith("2 logs: the iron shown in 2")


def test_ardupilots_sitl_flights_a_straight_line_shows_nothing(shared):
    """ArduPilot's SITL compass has no iron: the rover's turns show under 3 degrees; the copter flying a
    straight line turns too little to show anything, and says so."""
    folder = shared / "data" / "ardupilot-sitl"
    if not folder.is_dir():
        pytest.skip(f"{folder} is not here (the shared data folder sits beside the project)")
    got = tool(folder)
    assert got.returncode == 0, got.stderr
    lines = {line.split(":", 1)[0]: line for line in got.stdout.splitlines()}
    assert "up to " in lines["rover_clean_turns.tlog"]
    assert int(lines["rover_clean_turns.tlog"].split("up to ")[1].split()[0]) < 3
    assert lines["copter_clean_straight.tlog"].endswith("too few to show an iron")
    assert "not shown: its headings cover" in lines["copter_clean_straight.tlog"]


def test_a_missing_log_is_named_and_a_broken_one_skipped(tmp_path):
    got = tool(tmp_path / "nowhere.bin")
    assert got.returncode == 2 and "nowhere.bin: no such file or folder" in got.stderr and "Traceback" not in got.stderr
    (tmp_path / "broken.tlog").write_bytes(b"\xfe\x00garbage")
    got = tool(tmp_path)
    assert got.returncode == 0 and got.stdout.startswith("broken.tlog: skipped: "), got.stdout + got.stderr
