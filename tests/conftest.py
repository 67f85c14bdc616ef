"""Shared fixtures. The suite is in three folders, so that a change's blast radius shows:
unit/ (one layer at a time), integration/ (layers together, files), system/ (processes, sockets,
the harness; marked `slow`: `pytest -m "not slow"` leaves them out)."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def shared() -> Path:
    """The shared folder beside the project: the paper, design notes, real flight logs and autopilot tlogs."""
    return ROOT.parent / "shared"


@pytest.fixture(scope="module")
def runs():
    """Monitor runs that begin alike, their common beginning stepped once per test module (unit.synthetic.Runs)."""
    from unit.synthetic import Runs
    return Runs()


def pytest_collection_modifyitems(items):
    for item in items:
        if Path(str(item.fspath)).resolve().parent.name == "system":
            item.add_marker(pytest.mark.slow)
