"""The wheel, installed as an operator would: `guard demo`, `guard sim`, `guard replay` and `guard run` from a
fresh virtual environment, in a folder that is not the repository.

The wheel is built from a copy of the sources (no build/ in the repository) without build isolation, so no
network is needed. The new environment sees the test environment's dependencies through a .pth file, which
adds that site-packages folder to sys.path without running its .pth files: the editable install of guard
is not active there, and `guard` and `guard_sim` must come from the wheel.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import site
import socket
import subprocess
import sys
import threading
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
SOURCES = ("pyproject.toml", "README.md", "guard", "sim", "configs")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src, dist = tmp_path_factory.mktemp("src"), tmp_path_factory.mktemp("dist")
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(ROOT / name, src / name)
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                        str(dist), str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    (found,) = dist.glob("*.whl")
    return found


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> Path:
    """A fresh environment with the wheel installed, and the test environment's packages visible."""
    env = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env)], check=True, timeout=120)
    python = env / "bin" / "python"
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index",
                        "-q", str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    # after the install, so that pip never sees (nor touches) the editable guard of the test environment
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                             capture_output=True, text=True, check=True).stdout.strip()
    Path(purelib, "test-dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    return env


@pytest.fixture
def work(tmp_path) -> Path:
    """The current directory of every command: neither the repository nor the environment."""
    return tmp_path


def environ() -> dict:
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")} | \
        {"PYTHONNOUSERSITE": "1", "PYTHONUNBUFFERED": "1"}


def guard(venv: Path, *args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([str(venv / "bin" / "guard"), *args], capture_output=True, text=True, cwd=cwd,
                          env=environ(), timeout=timeout)


def test_the_wheel_holds_every_module_and_shipped_file(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    expected = {f"guard/{p.relative_to(ROOT / 'guard')}" for p in (ROOT / "guard").rglob("*.py")}
    expected |= {f"guard_sim/{p.relative_to(ROOT / 'sim')}" for p in (ROOT / "sim").glob("*.py")}
    expected |= {f"guard/configs/{p.name}" for p in (ROOT / "configs").glob("*.toml")}
    expected |= {f"guard_sim/scenarios/{p.name}" for p in (ROOT / "configs" / "scenarios").glob("*.toml")}
    expected |= {"guard/configs/systemd/guard.service", "guard/configs/guard.toml", "guard_sim/scenarios/paper.toml"}
    assert not expected - names, f"missing from the wheel: {sorted(expected - names)}"
    assert not [n for n in names if n.startswith(("sim/", "configs/"))], "a generic top-level name in the wheel"
    assert wheel.name.startswith("guard_nav-")
    entry = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "guard = guard.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()


def test_guard_and_the_simulator_come_from_the_wheel(venv, work):
    code = """if True:
        import importlib.util, json, guard, guard_sim, pymavlink
        from guard import resources
        from guard_sim import scenario
        print(json.dumps({"guard": guard.__file__, "guard_sim": guard_sim.__file__,
                          "config": str(resources.default_config_path()), "profiles": resources.profiles(),
                          "unit": str(resources.systemd_unit_path()), "scenarios": str(scenario.SCENARIO_DIR),
                          "names": scenario.names(), "sim": importlib.util.find_spec("sim") is not None,
                          "pymavlink": pymavlink.__file__}))"""
    r = subprocess.run([str(venv / "bin" / "python"), "-c", code], capture_output=True, text=True, cwd=work,
                       env=environ(), timeout=60)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    for key in ("guard", "guard_sim", "config", "unit", "scenarios"):
        assert Path(got[key]).is_relative_to(venv), (key, got[key])
    assert Path(got["config"]).is_file() and Path(got["unit"]).is_file()
    assert "guard-tight" in got["profiles"] and {"paper", "clean"} <= set(got["names"])
    assert not got["sim"], "a top-level `sim` is importable"
    assert not Path(got["pymavlink"]).is_relative_to(venv), "the dependencies are the test environment's"


def test_sim_then_replay(venv, work):
    r = guard(venv, "sim", "--scenario", "paper", "--tlog", "paper.tlog", cwd=work)
    assert r.returncode == 0, r.stderr
    assert (work / "paper.tlog").stat().st_size > 0 and (work / "paper.truth.json").is_file()
    r = guard(venv, "replay", "paper.tlog", "--report", "-", cwd=work)
    assert r.returncode == 0, r.stderr
    alarms = json.loads(r.stdout)["alarms"]
    assert alarms and 400 <= alarms[0]["gnss_index"] <= 405, alarms[:3]
    r = guard(venv, "sim", "--scenario", "nosuch", "--tlog", "x.tlog", cwd=work)
    assert r.returncode != 0 and "paper" in r.stderr, "the known scenarios are listed from the wheel"


def test_demo(venv, work):
    r = guard(venv, "demo", "--speedup", "20", cwd=work, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "GUARD ALARM" in r.stdout and "caught at sample" in r.stdout, r.stdout


def test_run_starts_and_stops_on_sigint(venv, work):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    p = subprocess.Popen([str(venv / "bin" / "guard"), "run", "--connect", f"udpin:127.0.0.1:{port}"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=work, env=environ())
    listening, lines = threading.Event(), []

    def read() -> None:
        for line in p.stdout:
            lines.append(line)
            if "listening on" in line:
                listening.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert listening.wait(30), (lines, p.poll())
        p.send_signal(signal.SIGINT)
        assert p.wait(15) == 0, p.stderr.read()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        reader.join(5)
        p.stdout.close()
        p.stderr.close()
