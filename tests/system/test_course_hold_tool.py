"""tools/course_hold.py: whether a receiver holds its course at low speed, per log."""

import dataclasses
import json
import subprocess
import sys

from conftest import ROOT
from guard_sim import scenario as scn
from guard_sim.run import run

SLOW = (1.5, 2.0, 1.0, 2.5, 1.5, 1.0)       # the clean route's legs at walking pace (m/s)


def tool(*args):
    return subprocess.run([sys.executable, str(ROOT / "tools" / "course_hold.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_a_simulated_receiver_holding_its_course_is_shown_and_one_that_does_not_is_not(tmp_path):
    """The route at 1 to 2.5 m/s for two minutes, its receiver holding its course below 1.5 m/s and not:
    every fix under the hold repeats its course and none over it; the held courses stand further from
    the track than the fresh ones; the other receiver repeats none. The two logs end to end (a reboot)
    are read to the end. A folder that is not there is an error naming it."""
    base = scn.load("clean")
    route = dataclasses.replace(base.route, waypoints_m=tuple((p[0], p[1], v)
                                                               for p, v in zip(base.route.waypoints_m, SLOW)))
    for name, hold in (("held", 1.5), ("free", 0.0)):
        sc = dataclasses.replace(base, duration_s=120.0, route=route,
                                 noise=dataclasses.replace(base.noise, gnss_course_hold_mps=hold))
        run(sc, 2, tlog=str(tmp_path / f"{name}.tlog"))
    got = tool(tmp_path, "--json", tmp_path / "out.json")
    assert got.returncode == 0, got.stderr
    by = {r["log"].rsplit("/", 1)[-1]: r for r in json.loads((tmp_path / "out.json").read_text())}
    held, free = by["held.tlog"], by["free.tlog"]
    under = [b for b in held["bins"] if b["to_mps"] <= 1.0 and b["fixes"]]
    over = [b for b in held["bins"] if b["from_mps"] >= 2.0 and b["fixes"]]
    assert under and over
    assert all(b["held"] >= b["fixes"] - 1 for b in under), held["bins"]      # the first of a stretch is fresh
    assert all(b["held"] == 0 for b in over), held["bins"]
    assert held["held_n"] > 100 and held["held_off_mps"] > 2 * held["fresh_off_mps"], held
    assert sum(b["held"] for b in free["bins"]) == 0 and free["held_n"] == 0
    assert "held.tlog: " in got.stdout and "course repeated by speed" in got.stdout
    # a reboot: the two logs end to end, the second's clock starting again, read on as a stretch of its own
    both = tmp_path / "both"
    both.mkdir()
    (both / "reboot.tlog").write_bytes((tmp_path / "held.tlog").read_bytes() + (tmp_path / "free.tlog").read_bytes())
    got = tool(both, "--json", tmp_path / "both.json")
    assert got.returncode == 0, got.stderr
    reboot = json.loads((tmp_path / "both.json").read_text())[0]
    assert reboot["fixes"] >= 0.95 * (held["fixes"] + free["fixes"]), (reboot["fixes"], held["fixes"], free["fixes"])
    missing = tool(tmp_path / "nowhere")
    assert missing.returncode == 2 and "nowhere: no such file or folder" in missing.stderr
