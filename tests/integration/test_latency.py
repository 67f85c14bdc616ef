"""A receiver that reports late: the simulator's GNSS latency, the filter's `gnss_delay_s` and the
latency's uncertainty `gnss_latency_sigma_air_s`.

A real receiver's fix shows the vehicle as it was 50 to 200 ms before its time stamp. In a turn the
velocity has rotated since, and on a speed change it has grown: a filter that compares the fix with
its current state reads the lag as an attack. With the latency modelled, the same drive is as quiet
as a receiver without latency, and a step is still caught at once. With the latency's uncertainty
set instead (off by default), the velocity's variance grows along the acceleration: the same drive
flown as an air vehicle is quiet too.
"""

import dataclasses

import pytest

from guard.config import parse
from guard.errors import ConfigError
from guard.runtime.replay import replay
from guard_sim import scenario
from guard_sim.run import run
from guard_sim.scenario import Attack

LAG_S = 0.2
ATTACK_S = 100.0


@pytest.fixture(scope="module")
def lagged_runs(tmp_path_factory):
    """Two minutes of the clean route's turns with a 0.2 s receiver latency, then a 5 m north step."""
    work = tmp_path_factory.mktemp("lag")
    base = scenario.load("clean")
    sc = dataclasses.replace(base, duration_s=120.0, noise=dataclasses.replace(base.noise, gnss_delay_s=LAG_S),
                             attacks=(Attack("step", "gnss_pos", "north", 5.0, ATTACK_S),))
    runs = []
    for seed in (11, 12, 13):
        tlog = work / f"lag-{seed}.tlog"
        truth = run(sc, seed, tlog=str(tlog))
        runs.append((tlog, truth["attacks"][0]["start_gnss_index"]))
    return runs


def ground(delay_s: float):
    return parse({"monitor": {"vehicle": "ground"}, "filter": {"gnss_delay_s": delay_s}}, "test")


def test_an_unmodelled_latency_reads_as_an_attack(lagged_runs):
    """The check that the simulator's latency bites: without the delay, turns raise GNSS alarms."""
    for tlog, k0 in lagged_runs:
        report = replay(str(tlog), ground(0.0))
        early = [a for a in report["alarms"] if a["gnss_index"] < k0]
        assert early and early[0]["sensor"] in ("gnss_pos", "gnss_vel"), f"{tlog.name}: no alarm before the attack"


def test_a_modelled_latency_is_quiet_and_the_step_still_caught(lagged_runs):
    for tlog, k0 in lagged_runs:
        report = replay(str(tlog), ground(LAG_S))
        alarms = report["alarms"]
        assert alarms, f"{tlog.name}: the step was missed"
        first = alarms[0]
        assert first["gnss_index"] >= k0, f"{tlog.name}: false alarm {first}"
        assert first["gnss_index"] <= k0 + 1 and (first["sensor"], first["channel"]) == ("gnss_pos", "north")


def air(latency_sigma_s: float | None = None):
    table: dict = {"monitor": {"vehicle": "air"}}
    if latency_sigma_s is not None:
        table["filter"] = {"gnss_latency_sigma_air_s": latency_sigma_s}
    return parse(table, "test")


def test_an_air_vehicle_held_by_the_latency_uncertainty(lagged_runs):
    """The same drives flown as an air vehicle, the latency not configured: by default the turns
    raise GNSS velocity alarms; with its uncertainty (0.15 s along the acceleration) none comes
    before the step, which is caught within a sample."""
    for tlog, k0 in lagged_runs:
        bare = replay(str(tlog), air())["alarms"]
        assert any(a["gnss_index"] < k0 and a["sensor"] == "gnss_vel" for a in bare), f"{tlog.name}: no bite"
        alarms = replay(str(tlog), air(0.15))["alarms"]
        assert alarms, f"{tlog.name}: the step was missed"
        first = alarms[0]
        assert first["gnss_index"] >= k0, f"{tlog.name}: false alarm {first}"
        assert first["gnss_index"] <= k0 + 1 and (first["sensor"], first["channel"]) == ("gnss_pos", "north")


@pytest.mark.parametrize("key", ["gnss_latency_sigma_s", "gnss_latency_sigma_air_s"])
@pytest.mark.parametrize("value", ["slow", -0.1, 1.5])
def test_a_bad_latency_sigma_is_named(key, value):
    with pytest.raises(ConfigError, match=f"filter: {key}|filter.{key}"):
        parse({"filter": {key: value}}, "test")


@pytest.mark.parametrize("value", ["fast", -0.1, 2.0])
def test_a_bad_latency_is_named(value):
    with pytest.raises(ConfigError, match="filter: gnss_delay_s|filter.gnss_delay_s"):
        parse({"filter": {"gnss_delay_s": value}}, "test")
