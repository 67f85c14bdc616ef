"""tools/compass_check.py: a PX4 flight's compass heading against the autopilot's own yaw; a log that
lacks a topic it needs is named with the topic, and a file that is no ULog with that."""

import importlib.util
import math
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT

TOOL = ROOT / "tools" / "compass_check.py"


def load():
    spec = importlib.util.spec_from_file_location("compass_check", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("roll_deg, pitch_deg", [(0.0, 0.0), (12.0, -8.0), (-25.0, 15.0)])
def test_a_compass_off_by_a_known_angle_reads_that_angle_however_tilted(roll_deg, pitch_deg):
    """The field of a site (inclination 64 degrees) seen by a body at yaw psi, rolled and pitched:
    levelled with that roll and pitch, its heading less an autopilot yaw 7 degrees short is 7 degrees."""
    cc = load()
    roll, pitch = math.radians(roll_deg), math.radians(pitch_deg)
    rows, yaws = [], []
    for psi in np.radians([-170.0, -60.0, 0.0, 45.0, 130.0]):
        inc = math.radians(64.0)
        ned = np.array([math.cos(inc), 0.0, math.sin(inc)]) * 0.48
        cy, sy, cp, sp, cr, sr = (math.cos(psi), math.sin(psi), math.cos(pitch), math.sin(pitch),
                                  math.cos(roll), math.sin(roll))
        r_nb = np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                         [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                         [-sp, sr * cp, cr * cp]])
        rows.append(r_nb.T @ ned)
        yaws.append(psi - math.radians(7.0))
    n = len(rows)
    got = cc.heading_less_yaw(np.array(rows), np.full(n, roll), np.full(n, pitch), np.array(yaws))
    assert np.allclose(got, 7.0, atol=1e-6), got


def test_a_log_without_a_topic_it_needs_is_named_with_it(shared, tmp_path):
    ulog = shared / "data" / "real" / "px4_vtol_cubeorange_short.ulg"
    if not ulog.is_file():
        pytest.skip(f"{ulog} is not here (the shared data folder sits beside the project)")
    (tmp_path / "notes.ulg").write_text("not a log")
    got = subprocess.run([sys.executable, str(TOOL), str(ulog), str(tmp_path / "notes.ulg")],
                         capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr
    lines = got.stdout.splitlines()
    assert lines[0] == f"{ulog}: skipped, it does not log estimator_states", lines
    assert lines[1].startswith(f"{tmp_path / 'notes.ulg'}: skipped, not a readable ULog"), lines
    assert "Traceback" not in got.stderr
