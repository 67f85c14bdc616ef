"""The clock check against the receiver's motion (guard.sources.clock) leaves the simulator's
clean drives as logged: a simulated clock keeps time, and a false correction would move every
figure of the evaluation."""

import dataclasses

import pytest

from guard.sources.clock import MOTION_TOLERANCE, motion_rate
from guard.sources.tlog import TlogReader
from guard_sim import scenario as scn
from guard_sim.run import run


@pytest.mark.parametrize("seed", [0, 1])
def test_a_simulated_clean_drive_keeps_its_clock(tmp_path, seed):
    sc = scn.load("clean")
    sc = dataclasses.replace(sc, duration_s=300.0)
    path = tmp_path / "clean.tlog"
    run(sc, seed, tlog=str(path))
    reader = TlogReader(str(path))
    try:
        assert not [n for n in reader.notes if "clock" in n], reader.notes
        rate, se, n = motion_rate(reader.track())
    finally:
        reader.close()
    assert n >= 10 and abs(rate - 1.0) < MOTION_TOLERANCE / 2 and se < 0.005, (rate, se, n)
