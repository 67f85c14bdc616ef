"""Shared fixtures. The suite is in three folders, so that a change's blast radius shows:
unit/ (one layer at a time), integration/ (layers together, files), system/ (processes, sockets,
the harness; marked `slow`: `pytest -m "not slow"` leaves them out).

And in two tiers, so that `make test` stays quick: a claim tested over seeds runs on its first
SEEDS_IN_MAKE_TEST of them there, and on all of them in `make test-long` (marked `long`), with the
few longest drives whose mechanism a quicker test of `make test` also checks (marked `long` where
they are written). Plain `pytest` runs both."""

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


SEEDS_IN_MAKE_TEST = 2     # a claim over seeds: how many of its seeds `make test` runs (the first ones listed)


def seed_rank(item) -> int:
    """The place of a test's seed among those its parametrize lists, where the seed is the only thing
    parametrized there (its further seeds: the same case again); 0 where it is not."""
    callspec = getattr(item, "callspec", None)
    if callspec is None or "seed" not in callspec.params:
        return 0
    for mark in item.iter_markers("parametrize"):
        if mark.args[0] in ("seed", ("seed",), ["seed"]):
            values = list(mark.args[1])
            return values.index(callspec.params["seed"]) if callspec.params["seed"] in values else 0
    return 0


def pytest_collection_modifyitems(items):
    for item in items:
        if Path(str(item.fspath)).resolve().parent.name == "system":
            item.add_marker(pytest.mark.slow)
        if seed_rank(item) >= SEEDS_IN_MAKE_TEST:
            item.add_marker(pytest.mark.long)
