"""`guard replay` fits the compass against the gyro (guard.runtime.deviation) and says a compass that
reads off by heading: its calibration or its place, where the readings before its first alarm show
it; where they turned too little, both that and what else fits alike, a field that came in flight, with
when the magnetometer's first alarm came. An attack on the compass is never put down to calibration."""

import dataclasses
import itertools
import json
import subprocess
import sys

import numpy as np
import pytest

from guard.model.samples import ImuSample
from guard.runtime import deviation
from guard.runtime.replay import replay
from guard.runtime.deviation import SAY_DEG, LiveCheck, said
from guard_sim import scenario as scn
from guard_sim.run import run
from guard_sim.scenario import Attack

DURATION_S = 300.0


def replayed(tmp_path, name: str, config: str = "", **noise) -> tuple[dict, list[str]]:
    """A clean loop (seed 3) with the compass's noise changed as asked, or with an attack on it; the
    report's compass fit and the summary's compass lines. `config`: a config file's text."""
    base = scn.load("clean")
    attacks = noise.pop("attacks", ())
    sc = dataclasses.replace(base, duration_s=DURATION_S, noise=dataclasses.replace(base.noise, **noise),
                             attacks=attacks)
    log = tmp_path / f"{name}.tlog"
    run(sc, 3, tlog=str(log))
    (tmp_path / "guard.toml").write_text(config)
    got = subprocess.run([sys.executable, "-m", "guard", "replay", str(log), "--report", str(tmp_path / f"{name}.json"),
                          "--config", str(tmp_path / "guard.toml")],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert got.returncode == 0, got.stderr
    report = json.loads((tmp_path / f"{name}.json").read_text())
    return report, [x for x in got.stdout.splitlines() if "the compass read" in x]


def test_a_compass_with_an_iron_from_the_start_is_said_and_a_clean_one_is_not(tmp_path):
    """An iron of 0.18 of the field (up to 10 degrees by heading) from the start: its first turn alarms
    before it has turned enough to show the iron, so the line says the iron over the whole log and
    what else would fit alike, with the first alarm's time. A clean compass: nothing said."""
    report, lines = replayed(tmp_path, "iron", mag_iron_x=0.15, mag_iron_y=-0.1)
    fitted = report["compass_deviation"]
    truth = np.degrees(np.arcsin(np.hypot(0.15, -0.1)))
    assert fitted["shown"] and abs(fitted["max_deviation_deg"] - truth) < 2.0, fitted
    first = min(a["time_usec"] for a in report["alarms"] if a["sensor"] == "mag") / 1e6
    assert fitted["before_first_alarm"]["shown"] is False, fitted
    assert len(lines) == 1 and "over the whole log" in lines[0] and "a field that came in flight" in lines[0], lines
    assert f"first alarm came at {first:.1f} s" in lines[0], lines
    report, lines = replayed(tmp_path, "clean")
    assert report["compass_deviation"]["max_deviation_deg"] < 2.0 and not lines, (report["compass_deviation"], lines)


@pytest.mark.parametrize("size, onset", [(0.08, 60.0), (0.05, 120.0)])
def test_an_attack_on_the_compass_is_not_put_down_to_its_calibration(tmp_path, size, onset):
    """A field added to the compass in flight fits as an iron over the whole log; the line, where
    there is one, never blames the calibration alone: it says a field that came in flight fits alike,
    and that the first alarm came when the attack began."""
    report, lines = replayed(tmp_path, "attack", attacks=(Attack("step", "mag", "x", size, onset),))
    mags = [a["time_usec"] / 1e6 for a in report["alarms"] if a["sensor"] == "mag"]
    assert mags and onset <= mags[0] <= onset + 3.0, mags          # caught as it began
    assert all("before its first alarm" not in x for x in lines), lines
    for x in lines:
        assert "a field that came in flight" in x and f"first alarm came at {mags[0]:.1f} s" in x, x
    if size >= 0.08:            # a field this large fits as an iron over the whole log, and the line says both
        assert len(lines) == 1, report["compass_deviation"]


def test_an_imu_slower_than_the_configured_rate_is_not_integrated_for_the_fit_either(tmp_path):
    """The fit integrates the gyro only where guard would (monitor.min_imu_hz): a 50 Hz IMU with the
    bound raised past it is not fitted, and the report says why."""
    report, lines = replayed(tmp_path, "slow", "[monitor]\nmin_imu_hz = 60.0\n", mag_iron_x=0.15, mag_iron_y=-0.1)
    fitted = report["compass_deviation"]
    assert not fitted["shown"] and "too slow to integrate the gyro" in fitted["error"] and not lines, fitted


def test_a_fit_within_its_own_error_or_that_explains_little_is_not_said():
    """The line needs a deviation of SAY_DEG beyond twice the fit's standard error, and a fit that takes
    the compass's scatter under EXPLAINS of what it is without."""
    d = np.sin(np.radians(8.0))
    good = {"shown": True, "dx": d, "dy": 0.0, "sigma": 0.01, "scatter_deg": 1.0, "scatter_without_deg": 5.0,
            "covered_deg": 300.0, "max_deviation_deg": 8.0}
    assert said(good) is not None and "over the whole log" in said(good)
    assert said({**good, "sigma": 0.03}) is None                                    # 8 degrees, within 2 sigma of 5
    assert said({**good, "scatter_deg": 4.0}) is None                               # explains too little
    assert said({**good, "max_deviation_deg": SAY_DEG - 0.1}) is None
    assert said({"shown": False, "why": "its headings cover 90 degrees"}) is None
    assert "before its first alarm" in said({"shown": False}, good, 30.0)


def test_a_long_log_full_of_gaps_is_fitted_on_its_longest_stretches_and_thinned():
    """An hour of compass readings cut by a gap every 11 s (360 stretches): the fit takes the
    MAX_STRETCHES longest and at most MAX_ROWS readings, in time order, so that its matrix stays small."""
    from guard.runtime import deviation as dev
    h = dev.Headings()
    rng = np.random.default_rng(1)
    for k in range(360):
        span = 10.1 + rng.uniform(0.0, 0.8)
        t = 11.0 * k + np.arange(0.0, span, dev.ROW_S)
        h.stretches.append([(x, 0.1 * (x - t[0]), 0.0) for x in t])
    t_rel, gamma, chi_m, stretch, t_abs = h.arrays()
    assert stretch.max() + 1 == dev.MAX_STRETCHES and len(t_rel) <= dev.MAX_ROWS
    assert np.all(np.diff(t_abs) > 0), "in time order"
    spans = sorted((r[-1][0] - r[0][0] for r in h.stretches), reverse=True)
    kept = [t_abs[stretch == j] for j in range(dev.MAX_STRETCHES)]
    assert min(k[-1] - k[0] for k in kept) >= spans[dev.MAX_STRETCHES - 1] - 2 * dev.ROW_S
    before = h.arrays(until_s=11.0 * 100)
    assert before[4].max() < 1100.0 and before[3].max() + 1 == dev.MAX_STRETCHES


def test_the_live_check_holds_the_latest_readings_only(monkeypatch):
    """guard run's check keeps the latest LIVE_ROWS readings: the oldest stretches go first, whole, then
    the oldest readings of the one left."""
    monkeypatch.setattr(deviation, "LIVE_ROWS", 120)
    check = LiveCheck(lambda line: None)
    check.stretches = [[(float(t), 0.0, 0.0) for t in range(100)], [(float(t), 0.0, 0.0) for t in range(200, 250)],
                       [(float(t), 0.0, 0.0) for t in range(300, 380)]]
    check._trim()
    assert [len(r) for r in check.stretches] == [40, 80] and check.stretches[0][0][0] == 210.0
    check.stretches = [[(float(t), 0.0, 0.0) for t in range(300)]]
    check._trim()
    assert len(check.stretches[0]) == 120 and check.stretches[0][0][0] == 180.0


def test_the_live_check_takes_the_samples_the_monitor_takes(tmp_path):
    """A frame sent again, and a lone wild stamp every 10 s, are dropped by the fit as the monitor drops
    them (they would otherwise cut the stretches short, and set the minute's fit off at once): the
    iron is still said, once, with its size."""
    base = scn.load("clean")
    sc = dataclasses.replace(base, duration_s=200.0,
                             noise=dataclasses.replace(base.noise, mag_iron_x=0.15, mag_iron_y=-0.1))
    log = tmp_path / "iron.tlog"
    run(sc, 3, tlog=str(log))
    n = itertools.count()

    def hostile(samples):
        for s in samples:
            yield s
            if isinstance(s, ImuSample):
                i = next(n)
                if i % 50 == 0:
                    yield s                                             # sent again
                if i % 500 == 250:
                    yield dataclasses.replace(s, t_us=s.t_us + 3_600_000_000)   # a wild stamp, an hour ahead
    said: list[str] = []
    check = LiveCheck(said.append)
    report = replay(str(log), listeners=[check], inject=hostile)
    assert report["skipped"].get("imu_resent") and report["skipped"].get("time_off_base"), report["skipped"]
    assert len(said) == 1, said
    size = float(said[0].split("up to ")[1].split(" deg")[0])
    assert abs(size - np.degrees(np.arcsin(np.hypot(0.15, -0.1)))) <= 2.0, said


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_gyro_bias_that_wanders_is_not_taken_for_an_iron(seed):
    """Ten minutes of a slow steady turn (1.5 degrees a second), the gyro's bias a new one every 100 s
    (0.01 degree/s, 1 sigma) and the compass's noise a degree: with no iron the fit finds under a
    degree; with one of 9.8 degrees it finds it within one. Each minute its own bias, the heading
    continuous across them (guard.runtime.deviation.drift_basis)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 600.0, 0.05)
    chi = np.radians(1.5) * t + 0.4
    bias = np.repeat(rng.normal(0.0, np.radians(0.01), 6), len(t) // 6 + 1)[:len(t)]
    gamma = chi - chi[0] + np.cumsum(bias) * 0.05
    noise = rng.normal(0.0, np.radians(1.0), len(t))
    for iron, truth in (((0.0, 0.0), 0.0), ((0.12, -0.12), np.degrees(np.arcsin(np.hypot(0.12, 0.12))))):
        chi_m = deviation.wrap(chi + deviation.deviations(chi, *iron)[0] + noise)
        d, _, cov = deviation.fit(t, gamma, chi_m, np.zeros(len(t), int))
        found = np.degrees(np.arcsin(np.hypot(*d)))
        assert abs(found - truth) < 1.0 and np.sqrt(max(cov[-1, -1], cov[-2, -2])) < deviation.MAX_SIGMA, (iron, d)
