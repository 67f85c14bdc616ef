"""Shared fixtures. The suite is in three folders, so that a change's blast radius shows:
unit/ (one layer at a time), integration/ (layers together, files), system/ (processes, sockets,
the harness; marked `slow`: `pytest -m "not slow"` leaves them out)."""

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def shared() -> Path:
    """The shared folder beside the project: the paper, design notes, real flight logs and autopilot tlogs."""
    return ROOT.parent / "shared"


@pytest.hookimpl(optionalhook=True)        # a hook of pytest-xdist: no error where it is not installed
def pytest_xdist_auto_num_workers(config):
    """`-n auto` or `-n logical` (make test): two workers per core, up to 16 (never fewer than one
    per core). The suite is mostly CPU-bound replays, but its system tests wait on sockets,
    processes and timeouts; a second worker per core runs while they wait (on 2 cores, one run
    each: 14.3 minutes against 16 to 17 with one per core, the same CPU time; README, `make test`).
    PYTEST_XDIST_AUTO_NUM_WORKERS still decides when set."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(cores, min(2 * cores, 16))


def pytest_collection_modifyitems(items):
    for item in items:
        if Path(str(item.fspath)).resolve().parent.name == "system":
            item.add_marker(pytest.mark.slow)
