"""The files shipped with guard: the documented default config, the profiles and the systemd unit.

They live in the repository's configs/ folder, which installs as the package `guard.configs` (see
pyproject.toml), and are found here through importlib.resources: the same in a wheel and in an editable
install, wherever the current directory is. The simulator's scenarios ship with it:
`guard_sim.scenario.names()`, `guard_sim.scenario.load(NAME)`.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from guard.errors import GuardError

PACKAGE = "guard.configs"
DEFAULT_CONFIG = "guard.toml"


def _file(*parts: str) -> Path:
    found = resources.files(PACKAGE).joinpath(*parts)
    if not isinstance(found, Path):     # a zipped install: guard reads its configs from the disk
        raise GuardError(f"{'/'.join(parts)}: guard's shipped files are not on the disk ({found})")
    return found


def default_config_path() -> Path:
    """The shipped guard.toml: every key at its default, with its units (a starting point for
    /etc/guard/guard.toml; guard reads its built-in defaults when no config is given)."""
    return _file(DEFAULT_CONFIG)


def profiles() -> list[str]:
    """The names of the shipped profiles (configs other than the default, e.g. guard-tight)."""
    return sorted(p.name.removesuffix(".toml") for p in resources.files(PACKAGE).iterdir()
                  if p.name.endswith(".toml") and p.name != DEFAULT_CONFIG)


def profile_path(name: str) -> Path:
    """The shipped profile `name` (one of profiles()), for --config."""
    if name not in profiles():
        raise GuardError(f"unknown profile {name!r} (known: {', '.join(profiles())})")
    return _file(f"{name}.toml")


def systemd_unit_path() -> Path:
    """The shipped systemd unit, guard.service."""
    return _file("systemd", "guard.service")
