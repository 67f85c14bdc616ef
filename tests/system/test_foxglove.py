"""Foxglove's own MCAP reader (@mcap/core, in node) reads a guard log, whose timeline starts at the
flight's UTC time (tools/foxglove-check). Skipped, saying so, where node and npm are not installed."""

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from guard.cli import main

ROOT = Path(__file__).resolve().parents[2]
CHECK = ROOT / "tools" / "foxglove-check"
NODE, NPM = shutil.which("node"), shutil.which("npm")
pytestmark = pytest.mark.skipif(NODE is None or NPM is None, reason="node and npm are not installed")


@pytest.fixture(scope="module")
def reader(tmp_path_factory):
    """A copy of tools/foxglove-check with its locked dependencies installed (from the npm registry)."""
    work = tmp_path_factory.mktemp("foxglove") / "check"
    shutil.copytree(CHECK, work, ignore=shutil.ignore_patterns("node_modules"))
    done = subprocess.run([NPM, "ci", "--no-audit", "--no-fund", "--silent"], cwd=work, capture_output=True,
                          text=True, timeout=300)
    if done.returncode != 0:
        pytest.skip(f"npm could not install @mcap/core: {done.stderr.strip()[-200:]}")
    return work


def test_foxglove_reads_a_guard_log_in_the_flights_utc_time(reader, shared, tmp_path):
    tlog = shared / "data" / "ardupilot-sitl" / "rover_clean_turns.tlog"
    if not tlog.exists():
        pytest.skip("the ArduPilot SITL tlogs are not in the shared data")
    log = tmp_path / "rover.mcap"
    assert main(["replay", str(tlog), "--mcap", str(log), "--report", str(tmp_path / "r.json")]) == 0
    out = subprocess.run([NODE, "check.mjs", str(log)], cwd=reader, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    seen = json.loads(out.stdout)
    first_prefix_us = int.from_bytes(tlog.read_bytes()[:8], "big")     # the ground station's clock
    assert abs(int(seen["start_ns"]) // 1000 - first_prefix_us) < 60e6, seen
    assert seen["start_utc"].startswith("2026-11-21"), seen                # the day the log was recorded
    assert seen["topics"]["/estimate/fix"] > 1000 and "/log" in seen["topics"] and seen["metadata"] == ["guard"]
