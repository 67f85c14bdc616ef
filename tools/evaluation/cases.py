"""The harness's cases: families of attacks on the simulator's clean drive, and each run's seed and config."""

from __future__ import annotations

import dataclasses
import tomllib

from guard.config import parse
from sim import scenario as scenarios
from sim.scenario import Attack

START_S = 30.0
ALL_FAMILIES = ("step", "ramp", "spoof", "freeze", "imu", "early", "clean", "paper")
SPOOF_PHASE_S = 9.0


def cases(families: list[str]) -> list[tuple[str, str, tuple[Attack, ...], float]]:
    """(family, case name, attacks, duration_s)."""
    out = []
    if "step" in families:
        for ch in ("north", "east"):
            for m in (1.0, 2.0, 5.0, 10.0, 20.0):
                out.append(("step", f"step {ch} {m:g} m", (Attack("step", "gnss_pos", ch, m, START_S),), 60.0))
    if "ramp" in families:
        for m in (0.05, 0.1, 0.3, 1.0, 2.0):
            out.append(("ramp", f"ramp north {m:g} m/s", (Attack("ramp", "gnss_pos", "north", m, START_S),), 90.0))
    if "spoof" in families:
        for ch in ("north", "east"):
            out.append(("spoof", f"spoof {ch} 0.05 m/s2", (Attack("spoof", "gnss_pos", ch, 0.05, START_S),), 105.0))
    if "freeze" in families:
        out.append(("freeze", "freeze", (Attack("freeze", "gnss_pos", "north", 0.0, START_S),), 60.0))
    if "imu" in families:
        out.append(("imu", "gyro z bias 0.05 rad/s", (Attack("bias", "gyro", "z", 0.05, START_S),), 60.0))
        out.append(("imu", "accel x bias 0.5 m/s2", (Attack("bias", "accel", "x", 0.5, START_S),), 60.0))
        out.append(("imu", "accel y bias 0.5 m/s2", (Attack("bias", "accel", "y", 0.5, START_S),), 60.0))
        out.append(("imu", "mag x bias 0.05 G", (Attack("bias", "mag", "x", 0.05, START_S),), 60.0))
        out.append(("imu", "mag x ramp 0.01 G/s", (Attack("ramp", "mag", "x", 0.01, START_S),), 60.0))
    if "early" in families:
        out.append(("early", "step north 5 m at sample 5", (Attack("step", "gnss_pos", "north", 5.0, 0.5),), 40.0))
    if "paper" in families:     # the paper's own scenario (its route, rates and attack), not the clean drive's
        paper = scenarios.load("paper")
        out.append(("paper", "paper scenario", paper.attacks, paper.duration_s))
    if "clean" in families:
        out.append(("clean", "clean 10 min", (), 600.0))
        drops = tuple(Attack("dropout", "gnss_pos", "north", 0.0, t, 5.0) for t in (60.0, 200.0, 400.0))
        out.append(("clean", "clean 10 min, GNSS dropouts", drops, 600.0))
    return out


def base_scenario(family: str, duration: float, attacks: tuple):
    """The scenario of one run: the paper's for its family, else the clean drive with the case's attacks."""
    base = scenarios.load("paper" if family == "paper" else "clean")
    return dataclasses.replace(base, name="eval", duration_s=duration, attacks=attacks)


def sim_seed(family: str, attacks: tuple, seed: int) -> int:
    """The simulator's seed for a campaign's seed: the same for every attack case (their differences
    are the attacks', not the noise's); the clean drives even, the ones with dropouts odd, so that
    every clean hour is a distinct one."""
    return 2 * seed + bool(attacks) if family == "clean" else seed


def phased(family: str, attacks: tuple, duration: float, seed: int) -> tuple[tuple, float]:
    """A spoof's physics depends on where the vehicle is on its route (along the track it looks like
    an accelerometer bias until a turn): its start moves 9 s a seed, over the route's first 81 s."""
    if family != "spoof":
        return attacks, duration
    shift = SPOOF_PHASE_S * (seed % 10)
    return tuple(dataclasses.replace(a, start_s=a.start_s + shift) for a in attacks), duration + shift


def detector_config(name: str, settings: tuple[str, ...] = ()):
    """guard's defaults with `settings` ("section.key=TOML value") applied, and the named detector."""
    table: dict = {"detector": {"name": name}}
    if name == "paper":      # as the paper describes it: restart the test, never stop fusing
        table["monitor"] = {"exclude_on_alarm": False}
    for item in settings:
        key, _, value = item.partition("=")
        section, _, field = key.strip().partition(".")
        table.setdefault(section, {})[field] = tomllib.loads(f"v = {value}")["v"]
    return parse(table, f"eval:{name} {' '.join(settings)}")
