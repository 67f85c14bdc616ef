from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def shared() -> Path:
    """The shared folder beside the project: the paper, design notes and real autopilot tlogs."""
    return Path(__file__).resolve().parents[2] / "shared"
