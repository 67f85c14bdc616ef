"""tools/damaged_logs.py: real logs, cut, flipped and holed, replayed through `guard replay` as a user
runs it: never a traceback; a cut log reads what comes before the cut, a flipped or holed one loses
only what the damage touched."""

import json
import subprocess
import sys

import pytest

from conftest import ROOT


def test_damaged_real_logs_lose_only_what_was_damaged(shared, tmp_path):
    logs = [shared / "data" / "real" / name for name in ("ardupilot_copter_pixhawk1_crash.bin",
                                                          "px4_vtol_cubeorange_short.ulg")]
    if not all(p.exists() for p in logs):
        pytest.skip("the shared real logs are not here (the shared data folder sits beside the project)")
    broken = tmp_path / "broken.tlog"
    broken.write_bytes(b"\xfe\x00garbage")                   # not a log at all: an error, not a traceback
    (tmp_path / "empty.ulg").write_bytes(b"")                # nor is an empty one, and it is not damaged
    got = subprocess.run([sys.executable, str(ROOT / "tools" / "damaged_logs.py"), *map(str, logs), str(broken), str(tmp_path / "empty.ulg"),
                          "--jobs", "2", "--json", str(tmp_path / "out.json")],
                         capture_output=True, text=True, timeout=600)
    assert got.returncode == 0, got.stdout + got.stderr
    assert "TRACEBACK" not in got.stdout, got.stdout
    lines = got.stdout.splitlines()
    assert lines[-5].startswith("4 logs, 2 read whole (2 not: 0 tracebacks)"), lines
    summary = {line.split(":")[0]: line for line in lines[-4:]}
    assert set(summary) == {"cut37", "cut71", "flips", "hole"}, lines
    share = {k: float(v.split("median ")[1].split(",")[0]) for k, v in summary.items()}
    assert share["cut37"] < 0.45 and 0.55 < share["cut71"] < 0.8, share
    assert share["flips"] > 0.95 and share["hole"] > 0.9, share
    results = json.loads((tmp_path / "out.json").read_text())
    assert [r["whole"]["status"] != 0 for r in results] == [False, False, True, True]
    assert "broken.tlog" in results[2]["whole"]["error"] and results[3]["copies"] == {}, results[2:]
