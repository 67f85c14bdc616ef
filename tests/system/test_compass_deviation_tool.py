"""tools/compass_deviation.py: a compass's hard iron fitted against the gyro, per log."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from guard.runtime.replay import replay
from guard.sources.base import as_logged
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
    assert "iron.tlog: up to " in got.stdout and got.stdout.splitlines()[-2].startswith("2 logs: the iron shown in 2")
    assert found["alarms_iron_out"] is not None and "with that iron out of its readings" in got.stdout
    assert got.stdout.splitlines()[-1].startswith("  their new alarms ")
    # the iron taken out of every reading, turned about the vertical: the fit then finds none
    cd = deviation_module()
    h = cd.Headings()
    replay(str(tmp_path / "iron.tlog"), listeners=[h], inject=cd.iron_out(*iron))
    out = cd.iron_of(h)
    assert out["shown"] and abs(out["dx"]) < 0.02 and abs(out["dy"]) < 0.02, out
    assert out["scatter_deg"] < found["scatter_without_deg"] / 3


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


def deviation_module():
    sys.path.insert(0, str(ROOT / "tools"))
    import compass_deviation
    return compass_deviation


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_motors_field_that_follows_the_throttle_is_told_from_the_iron(seed):
    """A compass whose body field is an iron plus the motors' field times the throttle, read over five
    minutes of turns while the throttle wanders: the fit finds the motors' field within 0.03 of the
    horizontal field, and with it the compass's scatter about the gyro falls to the readings' own
    noise; a compass with the iron alone shows no motors' field. The throttle is on the log's clock,
    which guard put on its receiver's (the report's `clock`)."""
    cd = deviation_module()
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 300.0, 0.1)
    gamma = 0.25 * t + 0.8 * np.sin(0.03 * t)                     # several turns, at a varying rate
    u = np.clip(0.5 + 0.15 * np.sin(0.11 * t + seed) + 0.05 * np.sin(0.7 * t), 0.1, 1.0)
    chi = 1.002 * gamma + 0.4 + 2e-4 * t                           # a gyro's scale and bias, a start
    clock = {"t0_usec": 5_000_000, "rate": 1.002}
    t_log = clock["t0_usec"] / 1e6 + (t + 100.0 - clock["t0_usec"] / 1e6) / clock["rate"]
    back = [as_logged(round(1e6 * x), (clock["t0_usec"], clock["rate"])) / 1e6
            for x in cd.on_samples_clock(t_log[::500], clock)]
    assert back == pytest.approx(t_log[::500], abs=1e-6)         # the log's clock taken as guard takes it back
    for m in ((0.25, -0.15), (0.0, 0.0)):
        d_x = 0.1 + m[0] * (u - np.median(u))
        d_y = -0.2 + m[1] * (u - np.median(u))
        dev = cd.deviations(chi, d_x, d_y)[0]
        chi_m = cd.wrap(chi + dev + rng.normal(0.0, np.radians(0.5), t.size))
        a = (t, gamma, chi_m, np.zeros(t.size, dtype=int), t + 100.0)
        got = cd.motors(a, np.column_stack([t_log, u]), clock)
        assert abs(got["mx"] - m[0]) < 0.03 and abs(got["my"] - m[1]) < 0.03, (m, got)
        if m != (0.0, 0.0):
            assert got["shown"] and got["scatter_deg"] < 0.8 < got["scatter_iron_only_deg"], got
        else:
            assert got["scatter_deg"] == pytest.approx(got["scatter_iron_only_deg"], rel=0.1), got


def test_the_throttle_is_read_on_the_compass_s_clock_from_dataflash_and_ulog(shared):
    """ArduCopter's CTUN.ThO and a PX4 VTOL's multicopter thrust while it hovers are read from 0 to 1
    on the log's own clock, which is the compass readings' (the crash flight's throttle spans its
    readings, and the motors' fit runs on them)."""
    cd = deviation_module()
    folder = shared / "data" / "real"
    if not folder.is_dir():
        pytest.skip(f"{folder} is not here (the shared data folder sits beside the project)")
    for name in ("ardupilot_copter_pixhawk1_crash.bin", "px4_vtol_cubeorange_short.ulg"):
        u, why = cd.throttle_of(str(folder / name))
        assert u is not None and why == "" and len(u) > 100 and np.all(np.diff(u[:, 0]) >= 0), (name, why)
        assert 0.0 <= u[:, 1].min() and u[:, 1].max() <= 1.0 and u[:, 1].max() > 0.3, name
    crash = str(folder / "ardupilot_copter_pixhawk1_crash.bin")
    h = cd.Headings()
    report = replay(crash, listeners=[h])
    readings = h.arrays()[4]
    u, _ = cd.throttle_of(crash)
    t = cd.on_samples_clock(u[:, 0], report.get("clock"))
    flying = t[u[:, 1] > cd.MIN_THROTTLE]
    assert flying[0] < readings[0] + 60 and readings[-1] - 10 < flying[-1] <= readings[-1] + 5, (flying[[0, -1]],
                                                                                                readings[[0, -1]])
    got = cd.motors(h.arrays(), u, report.get("clock"))
    assert "mx" in got and got["throttle_spread"] > 0.1, got


def test_a_tlog_s_throttle_is_not_read_and_said(tmp_path):
    """A tlog has no throttle on the autopilot's clock: the motors' field is said not fitted, and why."""
    cd = deviation_module()
    base = scn.load("clean")
    run(dataclasses.replace(base, duration_s=120.0), 2, tlog=str(tmp_path / "clean.tlog"))
    assert cd.throttle_of(str(tmp_path / "clean.tlog"))[0] is None
    got = tool(tmp_path, "--json", tmp_path / "out.json")
    assert got.returncode == 0, got.stderr
    why = json.loads((tmp_path / "out.json").read_text())[0]["motors"]["why"]
    assert why.startswith("a tlog's throttle (VFR_HUD) has no time of the autopilot's"), why
    assert f"  the motors' field: not fitted: {why}" in got.stdout


def test_an_older_copter_s_throttle_in_per_mille_and_a_plane_s_refused(tmp_path):
    """An older ArduCopter log's CTUN gives ThrOut in per mille and TimeMS: read as 0 to 1 and seconds;
    the same from an ArduPlane, whose throttle is its forward motor's, is not read, and said."""
    from guard_sim.dataflash import FMT, HEADER, MSG, LogFormat
    cd = deviation_module()
    ctun = LogFormat(140, "CTUN", "IhH", "TimeMS,ThrIn,ThrOut")
    for firmware, read in (("APM:Copter V3.2.1", True), ("ArduPlane V3.1.2", False)):
        path = tmp_path / f"{firmware.split()[0].replace(':', '')}.bin"
        with open(path, "wb") as f:
            for fmt in (FMT, MSG, ctun):
                f.write(HEADER + bytes((FMT.type,)) + FMT.body.pack(fmt.type, fmt.length, fmt.name.encode(),
                                                                     fmt.format.encode(), fmt.columns.encode()))
            f.write(HEADER + bytes((MSG.type,)) + MSG.body.pack(1000, firmware.encode()))
            for k in range(200):
                f.write(HEADER + bytes((ctun.type,)) + ctun.body.pack(20_000 + 100 * k, 500, 300 + 2 * k))
        u, why = cd.throttle_of(str(path))
        if read:
            assert why == "" and u.shape == (200, 2), why
            assert u[0, 0] == pytest.approx(20.0) and u[-1, 0] == pytest.approx(39.9)
            assert u[0, 1] == pytest.approx(0.3) and u[-1, 1] == pytest.approx(0.698)
        else:
            assert u is None and why == "its throttle is not a multicopter's lift (the log says plane)", why

