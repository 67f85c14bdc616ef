"""`guard replay` on a log that ends while a new time base waits to be confirmed: the samples held for
it are a stream's run, said as such, not as wild stamps; a lone wild stamp at the end is still one."""

import dataclasses

import pytest

from guard.model.samples import GnssFix, ImuSample
from guard.runtime.replay import replay
from guard_sim import scenario as scn
from guard_sim.run import run

SHIFT_US = 60_000_000


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    path = tmp_path_factory.mktemp("time") / "clean.tlog"
    run(dataclasses.replace(scn.load("clean"), duration_s=60.0), 2, tlog=str(path))
    return str(path)


def ending(last_s: float, lone: bool):
    """The log's last `last_s` seconds: its fixes gone and its IMU samples a minute ahead (the autopilot's
    clock set on, the receiver silent), or, `lone`, only its very last IMU sample so."""
    def inject(samples):
        samples = list(samples)
        end = max(s.t_us for s in samples if isinstance(s, ImuSample))
        out = []
        for s in samples:
            late = getattr(s, "t_us", 0) > end - last_s * 1e6
            if lone:
                out.append(dataclasses.replace(s, t_us=s.t_us + SHIFT_US) if isinstance(s, ImuSample) and
                           s.t_us == end else s)
            elif not (late and isinstance(s, GnssFix)):
                out.append(dataclasses.replace(s, t_us=s.t_us + SHIFT_US) if late and isinstance(s, ImuSample)
                           else s)
        return iter(out)
    return inject


def test_a_new_base_the_log_ended_before_confirming_is_said_as_such(log):
    """2 s of IMU samples (under the 3 s a stream alone needs to confirm a base) a minute ahead at the
    end, the receiver silent: counted as samples on a new base the log ended before confirming."""
    skipped = replay(log, inject=ending(2.0, lone=False))["skipped"]
    assert skipped.get("new_base_at_end", 0) >= 50 and "time_off_base" not in skipped, skipped


def test_a_lone_wild_stamp_at_the_end_is_still_one(log):
    skipped = replay(log, inject=ending(0.0, lone=True))["skipped"]
    assert skipped.get("time_off_base") == 1 and "new_base_at_end" not in skipped, skipped
