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


def pytest_collection_modifyitems(items):
    for item in items:
        if Path(str(item.fspath)).resolve().parent.name == "system":
            item.add_marker(pytest.mark.slow)
    # The order the workers take the files in (`make test` runs pytest-xdist with --dist loadfile
    # --no-loadscope-reorder): the files marked `heavy` first, then the others by their number of tests,
    # most first (xdist's own order, which put a file of a few long tests last: guard tune's ran alone at
    # the end for over two minutes while the other worker had nothing left). Each file's tests keep
    # their order.
    files: dict[str, list] = {}
    for i, item in enumerate(items):
        f = files.setdefault(item.nodeid.split("::")[0], [True, 0, i])
        f[0] = f[0] and item.get_closest_marker("heavy") is None
        f[1] -= 1
    items.sort(key=lambda item: files[item.nodeid.split("::")[0]])
