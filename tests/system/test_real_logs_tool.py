"""tools/real_logs.py: every log in a folder replayed, a line each and the totals; a bad key named
before any log runs."""

import subprocess
import sys

import pytest

from conftest import ROOT


def tool(*args):
    return subprocess.run([sys.executable, str(ROOT / "tools" / "real_logs.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_a_folder_of_logs_is_a_line_each_and_the_totals(shared, tmp_path):
    folder = shared / "data" / "ardupilot-sitl"
    if not folder.is_dir():
        pytest.skip(f"{folder} is not here (the shared data folder sits beside the project)")
    (tmp_path / "notes.txt").write_text("not a log")         # not a log's suffix: not listed
    (tmp_path / "broken.tlog").write_bytes(b"\xfe\x00garbage")
    got = tool(folder, tmp_path, "--json", tmp_path / "out.json")
    assert got.returncode == 0, got.stderr
    lines = got.stdout.splitlines()
    assert any(line.startswith("rover_clean_turns.tlog: tlog,") and "alarms 0 (none)" in line for line in lines)
    assert any(line.startswith("broken.tlog: skipped:") for line in lines), lines
    assert lines[-1].startswith("2 logs, ") and lines[-1].endswith("2 logs without one"), lines[-1]
    assert (tmp_path / "out.json").read_text().count('"log"') == 3


def test_a_bad_key_or_folder_is_named_and_nothing_runs(tmp_path):
    got = tool(tmp_path, "--set", "monitor.max_wander_factor=0.5")
    assert got.returncode == 2 and "monitor.max_wander_factor" in got.stderr and "Traceback" not in got.stderr
    got = tool(tmp_path / "nowhere")
    assert got.returncode == 2 and "nowhere: no such file or folder" in got.stderr
