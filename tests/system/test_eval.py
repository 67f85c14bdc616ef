"""A reduced evaluation campaign (the harness in tools/eval.py, a couple of minutes): the detectors
side by side on steps, a freeze and an early attack, with the figures asserted."""

import json
import math
from pathlib import Path

import pytest
from toolbox import load_tool

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def harness():
    return load_tool("eval", as_name="guard_eval")    # its worker processes find the job function by it


@pytest.fixture(scope="module")
def summary(harness, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    assert harness.main(["--quick", "--families", "step", "freeze", "early", "--seeds", "2",
                         "--detectors", "cusum", "gate", "--out", str(out), "--jobs", "2"]) == 0
    assert (out / "runs.csv").stat().st_size > 0 and (out / "delay_vs_step.png").stat().st_size > 0
    rows = json.loads((out / "summary.json").read_text())
    # an earlier campaign summarised again from its runs.csv gives the same summary
    assert harness.main(["--summarise", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text()) == rows
    return {(s["case"], s["detector"]): s for s in rows}


def test_steps_are_caught_at_once_and_isolated(summary):
    for ch in ("north", "east"):
        for size in ("2", "10"):
            s = summary[(f"step {ch} {size} m", "cusum")]
            assert s["detection_rate"] == 1.0 and s["isolation_rate"] == 1.0
            assert s["p95_delay_samples"] <= 3 and s["p95_delay_s"] <= 1.0     # within 1 s at 10 Hz
            assert s["false_alarms_per_h"] == 0


def test_cusum_beats_the_autopilot_gate(summary):
    """The 5-sigma gate with 1 s persistence needs 10 samples on a 10 m step; CUSUM needs none."""
    cusum, gate = summary[("step north 10 m", "cusum")], summary[("step north 10 m", "gate")]
    assert cusum["median_delay_samples"] == 0
    assert gate["median_delay_samples"] >= 9
    assert summary[("step north 2 m", "gate")]["detection_rate"] < 1.0


def test_freeze_within_one_sample_and_early_attack_caught(summary):
    freeze = summary[("freeze", "cusum")]
    assert freeze["detection_rate"] == 1.0 and freeze["p95_delay_samples"] <= 1
    early = summary[("step north 5 m at sample 5", "cusum")]
    assert early["detection_rate"] == 1.0 and early["median_delay_samples"] <= 1


def test_estimate_stays_within_5_m_for_30_s_after_the_alarm(summary):
    for case in ("freeze", "step north 10 m", "step east 2 m"):
        assert summary[(case, "cusum")]["worst_error_30s_after_m"] < 5.0, case


def test_one_run_on_request(harness, tmp_path, capsys):
    assert harness.main(["--figure", "freeze", "1", "--out", str(tmp_path)]) == 0
    stem = tmp_path / "freeze-seed1"
    report = json.loads(stem.with_suffix(".json").read_text())
    assert report["alarms"][0]["channel"] == "frozen" and stem.with_suffix(".png").stat().st_size > 0
    assert (f"first alarm at GNSS sample {report['alarms'][0]['gnss_index']} (gnss_pos frozen)"
            in capsys.readouterr().out)
    assert harness.main(["--figure", "no such case", "1", "--out", str(tmp_path)]) == 2
    assert "the cases are" in capsys.readouterr().err


def test_one_run_through_another_detector(harness, tmp_path):
    """--figure replays through the first of --detectors: the autopilots' gate holds a 10 m step
    for its persistence time before it alarms, the CUSUM takes it at once."""
    first = {}
    for det in ("cusum", "gate"):
        assert harness.main(["--figure", "step north 10 m", "1", "--out", str(tmp_path / det), "--detectors", det]) == 0
        report = json.loads((tmp_path / det / "step_north_10_m-seed1.json").read_text())
        assert report["detector"] == det
        first[det] = report["alarms"][0]["gnss_index"]
    assert first["gate"] - first["cusum"] >= 5, first


def test_one_run_with_a_config_file(harness, tmp_path, capsys):
    """--config applies a guard TOML file, as --set does: the same run replayed with a heading
    trusted 100 times less finds the gyro bias later (the heading is what shows it); a key guard
    does not know stops the harness with the key named."""
    case, stem = "gyro z bias 0.05 rad/s", "gyro_z_bias_0.05_rad_s-seed1"
    first = {}
    for label, extra in (("default", []), ("loose", ["--config", str(tmp_path / "loose.toml")])):
        (tmp_path / "loose.toml").write_text("[filter]\nheading_sigma_rad = 3.0\n")
        assert harness.main(["--figure", case, "1", "--out", str(tmp_path / label), *extra]) == 0
        alarms = json.loads((tmp_path / label / f"{stem}.json").read_text())["alarms"]
        first[label] = alarms[0]["gnss_index"] if alarms else 10 ** 9
    assert first["loose"] > first["default"], first
    (tmp_path / "bad.toml").write_text("[filter]\nq_vel = 1\n")
    assert harness.main(["--config", str(tmp_path / "bad.toml"), "--families", "spoof", "--out", str(tmp_path)]) == 2
    assert "filter.q_vel: unknown key" in capsys.readouterr().err


def test_delay_is_near_the_lorden_bound_for_steps(summary):
    for ch in ("north", "east"):
        s = summary[(f"step {ch} 2 m", "cusum")]
        assert s["lorden_bound_samples"] > 0
        assert s["delay_over_lorden"] <= 2.0


def test_false_alarm_extrapolation_follows_the_tail_and_declines_too_few_runs(harness):
    """Runs of one hour whose peaks fall off tenfold per 0.2 of scale from half of them at 0.5:
    carried to the threshold that is one run in 632 hours. Ten runs are too few to say anything."""
    import math
    n = 1000
    peaks = [0.5 + math.log10(0.5 / u) / 5 if u < 0.5 else 0.3 for u in ((i + 0.5) / n for i in range(n))]
    rows = [{"peak_ratio": p, "hours": 1.0} for p in peaks]
    expected = 1 / (0.5 * 10 ** -2.5)
    assert harness.extrapolate(rows) == pytest.approx(expected, rel=0.2)
    assert harness.extrapolate(rows[::100]) is None


def test_an_interrupted_campaign_resumes_where_it_stopped(harness, tmp_path, capsys):
    attacks = (harness.Attack("step", "gnss_pos", "north", 5.0, 10.0),)
    jobs = [("step", "resume", attacks, 15.0, seed, ("cusum",), str(tmp_path), ()) for seed in (0, 1)]
    whole = harness.campaign(jobs, tmp_path, 2, resume=False)
    assert [r["seed"] for r in whole] == [0, 1] and all(r["detected"] for r in whole)
    partial = tmp_path / harness.PARTIAL
    lines = partial.read_text().splitlines()
    assert len(lines) == 2
    # the interruption: one job's line whole, the other's cut mid-write
    first = next(line for line in lines if json.loads(line)["rows"][0]["seed"] == 0)
    partial.write_text(first + "\n" + lines[1][:40])
    capsys.readouterr()
    again = harness.campaign(jobs, tmp_path, 2, resume=True)
    assert "resuming: 1 of 2 runs" in capsys.readouterr().err
    assert again == whole, "the resumed campaign gives the same rows, in the jobs' order"
    assert [json.loads(line)["rows"][0]["seed"] for line in partial.read_text().splitlines()] == [0, 1]
    # without --resume the leftovers are discarded and every job runs
    harness.campaign(jobs, tmp_path, 2, resume=False)
    assert "resuming" not in capsys.readouterr().err


def test_an_interrupted_campaign_is_not_overwritten_unasked(harness, tmp_path, capsys):
    (tmp_path / harness.PARTIAL).write_text('{"key": "[]", "rows": []}\n')
    assert harness.main(["--families", "early", "--seeds", "1", "--detectors", "cusum", "--out", str(tmp_path)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert (tmp_path / harness.PARTIAL).read_text().startswith('{"key"'), "left as it was"


def test_a_vehicle_s_early_step_is_at_its_fifth_fix_and_its_bound_at_its_own_rate(harness):
    """The second family's early step starts at GNSS sample 5 of each vehicle's rate (not at 0.5 s,
    the second fix of a 2 Hz receiver), and Lorden's bound is per vehicle: the same innovation
    variance gives the same bound in samples, so twice the seconds at half the rate."""
    from tools.evaluation.cases import EARLY_SAMPLE, base_scenario, cases, vehicle
    from tools.evaluation.summary import lorden
    (family, _, attacks, duration), = cases(["early"])
    for seed in range(12):
        car = vehicle(seed)
        sc = base_scenario(family, duration, attacks, car)
        assert sc.rates.gnss_hz == car["gnss_hz"]
        assert sc.route.sideslip_rad_per_mps2 == car["sideslip_rad_per_mps2"] <= 0.015
        assert sc.route.max_yaw_jerk_radps3 == car["max_yaw_jerk_radps3"] >= 1.0
        assert sc.route.sensors_ahead_m == car["sensors_ahead_m"] and -0.5 <= car["sensors_ahead_m"] <= 1.5
        assert sc.noise.imu_yaw_mount_deg == car["imu_yaw_mount_deg"]
        assert sc.noise.mag_hz == car["mag_hz"] and 10.0 <= car["mag_hz"] <= 100.0
        assert sc.attacks[0].start_s == pytest.approx(EARLY_SAMPLE / car["gnss_hz"])
    assert base_scenario(family, duration, attacks).attacks[0].start_s == pytest.approx(EARLY_SAMPLE / 10.0)
    slow, fast = ({"S_pos": 0.3, "vehicle": json.dumps({"gnss_hz": hz})} for hz in (1.0, 2.0))
    (b1, hz1), (b2, hz2) = lorden(2.0, slow, 1000.0), lorden(2.0, fast, 1000.0)
    assert b1 < b2 < b1 * 1.1 and b1 / hz1 > 1.8 * b2 / hz2      # ln(ARL0) grows with the rate, slowly
    assert b1 == pytest.approx(math.log(1000 * 3600) / (4 / 0.6))


def test_the_information_bound_of_growing_attacks():
    """A ramp or a bias grows in the innovations: the bound is the time at which the information its
    samples carry reaches ln(ARL0). A constant signal gives Lorden's bound; a noisier or slower
    receiver, a later one; an accelerometer bias, seen in velocity and position, an earlier one than
    in velocity alone."""
    from tools.evaluation.summary import growing_bounds, information_bound, lorden, signature
    step = (("gnss_pos", lambda t: 2.0),)
    samples, _ = lorden(2.0, {"S_pos": 1.0, "vehicle": {"gnss_hz": 1.0}}, 1000.0)
    assert information_bound(step, {"gnss_pos": 1.0}, {"gnss_pos": 1.0}, 1000.0) == math.ceil(samples)
    ramp = signature("ramp north 0.3 m/s")
    quiet = information_bound(ramp, {"gnss_pos": 0.3}, {"gnss_pos": 10.0}, 1000.0)
    noisy = information_bound(ramp, {"gnss_pos": 4.0}, {"gnss_pos": 10.0}, 1000.0)
    slow = information_bound(ramp, {"gnss_pos": 4.0}, {"gnss_pos": 1.0}, 1000.0)
    assert quiet < noisy < slow
    # the sum over samples of (v t)^2 / 2S reaches ln(ARL0) between the sample before and the bound
    need = math.log(1000 * 3600 * 1.0)
    info = lambda T: sum((0.3 * i) ** 2 / 8.0 for i in range(1, int(T) + 1))     # noqa: E731
    assert info(slow - 1) < need <= info(slow)
    accel = signature("accel x bias 0.5 m/s2")
    S, hz = {"gnss_pos": 4.0, "gnss_vel": 0.07}, {"gnss_pos": 1.0, "gnss_vel": 1.0}
    assert information_bound(accel, S, hz, 1000.0) <= information_bound(accel[:1], S, hz, 1000.0)
    assert information_bound(signature("gyro z bias 0.05 rad/s"), {"mag": 4e-4}, {"mag": None}, 1000.0) is None
    # a coordinated spoof accelerating away at a: the trace of an accelerometer bias of that size, 10x smaller
    spoof = signature("spoof north 0.05 m/s2")
    assert [k for k, _ in spoof] == [k for k, _ in accel] and spoof[0][1](2.0) == pytest.approx(0.1)
    assert information_bound(spoof, S, hz, 1000.0) > information_bound(accel, S, hz, 1000.0)
    assert signature("freeze") is None and signature("step north 2 m") is None
    # per run of a summary row: guard's time from the onset (its delay plus one GNSS sample) over it
    row = {"case": "ramp north 0.3 m/s"}
    runs = [{"S_pos": 4.0, "delay": 20, "delay_s": 20.0, "vehicle": json.dumps({"gnss_hz": 1.0})},
            {"S_pos": 0.3, "delay": None, "delay_s": None, "vehicle": json.dumps({"gnss_hz": 10.0})}]
    growing_bounds(row, runs, 10.0, 1000.0)
    assert row["information_bound_s_max"] == slow and row["delay_over_bound"] == pytest.approx(21.0 / slow)


def test_a_run_records_what_the_bounds_need(harness):
    """One run of a gyro attack on a drawn vehicle carries its velocity and heading innovation
    variances and the rate the heading was tested at (the IMU's)."""
    import tempfile
    from tools.evaluation.cases import cases
    from tools.evaluation.runs import one
    family, name, attacks, duration = next(c for c in cases(["imu"]) if c[1].startswith("gyro"))
    with tempfile.TemporaryDirectory() as work:
        row, = one((family, name, attacks, duration, 3, ("cusum",), work, (), True))
    assert row["S_vel"] > 0 and row["S_pos"] > row["S_vel"] > 0 and row["S_mag"] > 0
    assert row["mag_hz"] == pytest.approx(json.loads(row["vehicle"])["imu_hz"], rel=0.1)
    # the alarm's own time from the onset: within one GNSS period of its delay in GNSS samples
    gnss_hz = json.loads(row["vehicle"])["gnss_hz"]
    assert row["delay_s"] - 1e-6 <= row["onset_delay_s"] <= row["delay_s"] + 1 / gnss_hz + 1e-6


def test_an_imu_alarm_before_the_first_attacked_fix_is_the_attack_s(harness):
    """An accelerometer attack caught on its first IMU sample, before the next GNSS fix (whose index
    the alarm then carries), is a detection at 0 samples, not a false alarm and a miss. (Without the
    shock bound the accelerometer's test fires on that first sample.)"""
    import tempfile
    from guard_sim.scenario import Attack
    from tools.evaluation.cases import START_S
    from tools.evaluation.runs import one
    with tempfile.TemporaryDirectory() as work:
        row, = one(("imu", "accel x bias 10 m/s2", (Attack("bias", "accel", "x", 10.0, START_S),), 40.0, 0,
                    ("cusum",), work, ("detector.shock_sigma=0",)))
    assert row["false_alarms"] == 0 and row["detected"] and row["delay"] == 0
    assert row["first_sensor"] == "accel x"
