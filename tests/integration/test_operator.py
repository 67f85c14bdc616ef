"""What an operator meets first: `guard config`, the help, `mcap-recover` that keeps its input, a log
directory the daemon cannot write, and an MCAP log in the flight's own time that keeps its alarms and
the operator's warnings."""

import datetime
import tomllib
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from guard.cli import main
from guard.config import Config, dump, load, parse
from guard.errors import ConfigError
from guard.model.events import Alarm, Estimate
from guard.runtime.daemon import Daemon
from guard.sinks.mcap import McapLog

SITL = "ardupilot-sitl/copter_clean_straight.tlog"


def test_guard_config_prints_every_key_and_reads_back(tmp_path, capsys):
    path = tmp_path / "rover.toml"
    path.write_text('[monitor]\nvehicle = "ground"\n[detector]\nfalse_alarm_interval_h = 2000.0\n')
    assert main(["config", "--config", str(path), "--connect", "tcp:127.0.0.1:5760", "--system-id", "10"]) == 0
    out = capsys.readouterr().out
    assert f"# file: {path}" in out
    assert "detector.false_alarm_interval_h, monitor.vehicle" in out and "link.connect (--connect)" in out
    assert "link.system_id (--system-id)" in out
    cfg = parse(tomllib.loads(out), "printed")
    assert cfg.monitor.vehicle == "ground" and cfg.monitor.detector.false_alarm_interval_h == 2000.0
    assert cfg.link.connect == "tcp:127.0.0.1:5760" and cfg.link.system_id == 10
    # every key is there, the defaults included: the printed file is the whole configuration
    expected = load(str(path))
    assert dump(cfg) == dump(Config(link=cfg.link, can=expected.can, log=expected.log, monitor=expected.monitor))


def test_a_compass_offset_west_is_read_and_a_negative_noise_refused_by_its_key(tmp_path):
    # guard tune writes the offset it learnt, negative for a compass that reads west of the heading
    path = tmp_path / "vehicle.toml"
    path.write_text("[filter]\nmag_offset_rad = -0.07\n")
    assert load(str(path)).monitor.filter.mag_offset_rad == -0.07
    path.write_text("[filter]\nmag_offset_rad = -4.0\n")
    with pytest.raises(ConfigError, match=r"filter\.mag_offset_rad: must be within -pi\.\.pi"):
        load(str(path))
    path.write_text("[filter]\ngnss_vel_sigma_mps = -0.1\n")
    with pytest.raises(ConfigError, match=r"filter\.gnss_vel_sigma_mps: must be a finite number >= 0"):
        load(str(path))


def test_verbose_goes_before_or_after_the_command(tmp_path, capsys):
    assert main(["config", "-v"]) == 0 and main(["-v", "config"]) == 0


def test_mcap_recover_never_overwrites_its_input(tmp_path, capsys):
    log = McapLog(str(tmp_path / "cut.mcap"))
    log.on_events([Alarm(2_000_000, 3, "gnss_pos", "north", 12.0, 10.0, 9.0, "cusum")])
    cut = Path(log.path)
    size = cut.stat().st_size
    assert main(["mcap-recover", str(cut), str(cut)]) == 1
    assert "is the log to recover" in capsys.readouterr().err and cut.stat().st_size == size
    other = tmp_path / "other.mcap"
    other.write_bytes(b"keep me")
    assert main(["mcap-recover", str(cut), str(other)]) == 1
    assert "--force" in capsys.readouterr().err and other.read_bytes() == b"keep me"
    assert main(["mcap-recover", str(cut), str(other), "--force"]) == 0
    log.close()


def test_an_alarm_is_on_the_disk_at_once(tmp_path):
    """The chunk holding an alarm is finished and synced when the alarm is written: a kill right after
    it (the process never closes the log) leaves the alarm readable."""
    log = McapLog(str(tmp_path / "run.mcap"), chunk_size=1 << 20)
    for i in range(50):
        log.on_events([Estimate(1_000_000 + i * 100_000, i, 0.0, 0.0, 0.0, np.zeros(12), np.ones(12),
                                (47.0, 8.0, 400.0))])
    log.on_events([Alarm(6_000_000, 50, "gnss_pos", "north", 12.0, 10.0, 9.0, "cusum")])
    with open(log.path, "rb") as f:            # what another process (or a recovery) finds on the disk
        topics, channels = [], {}
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if type(rec).__name__ == "Channel":
                    channels[rec.id] = rec.topic
                elif type(rec).__name__ == "Message":
                    topics.append(channels[rec.channel_id])
        except Exception:                       # the unfinished file ends mid-record: what came before counts
            pass
    assert "/alarms" in topics and topics.count("/estimate/state") == 50
    log.close()


def test_an_unwritable_log_directory_is_an_error_before_the_link_opens(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    daemon = Daemon(Config(), connect="udpin:127.0.0.1:0", mcap=str(blocker / "logs"))
    with pytest.raises(ConfigError, match="log.mcap"):
        daemon.startup()
    assert daemon.source is None                # nothing was opened


def test_the_operators_warnings_are_in_the_log(tmp_path):
    daemon = Daemon(Config(), connect="udpin:127.0.0.1:0")
    daemon.log = McapLog(str(tmp_path / "run.mcap"))
    daemon._operator("no IMU data for 5 s: waiting", send=False)
    daemon._core_notice("a core notice the log has already", send=False)
    daemon.log.close()
    with open(tmp_path / "run.mcap", "rb") as f:
        logs = [message.data for _, _, message in make_reader(f).iter_messages(topics=["/log"])]
    assert len(logs) == 1 and b"no IMU data for 5 s" in logs[0]


def test_a_replayed_log_is_in_the_flights_utc_time(shared, tmp_path):
    tlog = shared / "data" / SITL
    if not tlog.exists():
        pytest.skip(f"{SITL} is not in the shared data")
    out = tmp_path / "replay.mcap"
    assert main(["replay", str(tlog), "--mcap", str(out), "--report", str(tmp_path / "r.json")]) == 0
    first_prefix = int.from_bytes(tlog.read_bytes()[:8], "big")        # the ground station's clock, unix us
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        start_us = summary.statistics.message_start_time // 1000
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        _, _, state = next(reader.iter_messages(topics=["/estimate/state"]))
    # the timeline starts at the flight's time (within the log's first seconds), not at 1970
    assert abs(start_us - first_prefix) < 60e6, (start_us, first_prefix)
    assert datetime.datetime.fromtimestamp(start_us / 1e6, datetime.timezone.utc).year >= 2020
    # the vehicle's own time stays in the records; the configuration in effect is stored whole
    import json
    t_boot = json.loads(state.data)["t_us"]
    assert t_boot < 1e12 and state.log_time // 1000 - t_boot > 1e15
    assert parse(tomllib.loads(meta["guard"]["config_in_effect"]), "meta") == Config()


def test_the_figure_shows_the_alarmed_axis_and_explains_every_mark(tmp_path, monkeypatch):
    """An east step: the figure is about GNSS position east (not north, as it once always was), its
    attack and the exclusion are shaded, and every kind of mark has a legend entry."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from guard.runtime.replay import replay, truth_beside
    from guard.sinks import plot as figure
    import dataclasses
    from guard_sim import scenario as scenarios
    from guard_sim.run import run
    from guard_sim.scenario import Attack
    sc = dataclasses.replace(scenarios.load("clean"), duration_s=45.0,
                             attacks=(Attack("step", "gnss_pos", "east", 10.0, 25.0),))
    tlog = tmp_path / "east.tlog"
    run(sc, 3, tlog=str(tlog))
    trace = figure.Trace()
    report = replay(str(tlog), listeners=[trace])
    assert report["alarms"] and report["alarms"][0]["channel"] == "east"
    assert figure.shown_channel(trace, report) == ("gnss_pos", "east")
    saved = {}
    monkeypatch.setattr(plt.Figure, "savefig", lambda fig, out, **kw: saved.setdefault("fig", fig))
    figure.plot(trace, report, str(tmp_path / "east.png"), truth_beside(str(tlog)))
    axes = saved["fig"].axes
    assert axes[0].get_ylabel().startswith("east") and "gnss_pos east" in axes[2].get_ylabel()
    labels = axes[2].get_legend_handles_labels()[1]
    for kind in ("statistic", "threshold", "excluded", "guard alarm", "attack: step on gnss_pos east"):
        assert any(kind in label for label in labels), (kind, labels)


def test_a_udp_port_already_taken_is_refused():
    """A second guard (or a router) on the same UDP port would otherwise share it silently (pymavlink
    binds with SO_REUSEADDR): the one that comes second says so and does not start."""
    import socket
    from guard.config import LinkConfig
    from guard.errors import SourceError
    from guard.sources.link import MavlinkLink
    first = MavlinkLink("udpin:127.0.0.1:0", LinkConfig())           # the first, as pymavlink binds it
    port = first.conn.port.getsockname()[1]
    try:
        with pytest.raises(SourceError, match=f"UDP port {port} is in use"):
            MavlinkLink(f"udpin:127.0.0.1:{port}", LinkConfig())
    finally:
        first.close()
    free = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    MavlinkLink(f"udpin:127.0.0.1:{port}", LinkConfig()).close()      # a free port opens


def test_only_the_link_guard_reads_from_asks_the_autopilot_for_streams():
    """The ground station's link (link.gcs), or the MAVLink link that only carries a CAN source's
    alarms, may hear the autopilot's HEARTBEAT through a router: guard reads no stream there, so it
    asks for none (the autopilot would send them for nothing)."""
    from guard.config import LinkConfig
    from guard.core.monitor import MonitorConfig
    from guard.sources.link import MavlinkLink
    links = []
    try:
        links.append(MavlinkLink("udpin:127.0.0.1:0", LinkConfig(), MonitorConfig().min_imu_hz))
        links.append(MavlinkLink("udpin:127.0.0.1:0", LinkConfig()))
        data, send_only = links
        assert data.rates is not None and data.rates.enough_hz == MonitorConfig().min_imu_hz
        assert send_only.rates is None
    finally:
        for link in links:
            link.close()


def test_a_replay_says_how_far_the_estimate_stood_from_the_fixes_and_what_it_skipped(shared, tmp_path, capsys):
    """The summary a replay prints: the estimate's distance from the fixes (a clean flight: within a
    few metres), and a line in words for each reason something was skipped; the report has both."""
    tlog = shared / "data" / SITL
    if not tlog.exists():
        pytest.skip(f"{SITL} is not in the shared data")
    assert main(["replay", str(tlog), "--report", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out.splitlines()
    import json
    report = json.loads((tmp_path / "r.json").read_text())
    gap = report["estimate_to_fix_m"]
    assert gap["fixes"] > 0.9 * report["gnss_samples"] and gap["max"] < 3.0, gap
    said = [line for line in out if "the estimate from the fixes" in line]
    assert len(said) == 1 and f"{gap['max']:.1f} m at most" in said[0], out
    skipped = [line.strip() for line in out if line.strip().startswith("skipped ")]
    assert len(skipped) == len(report["skipped"]) and report["skipped"], (out, report["skipped"])
    assert not any("_" in line for line in skipped), skipped          # words, not the report's keys


def north_step(tmp_path, seed: int):
    """A simulated 40 s drive, its GNSS position stepped 10 m north from 25 s to the end, as a tlog."""
    import dataclasses
    from guard_sim import scenario as scenarios
    from guard_sim.run import run
    from guard_sim.scenario import Attack
    sc = dataclasses.replace(scenarios.load("clean"), duration_s=40.0,
                             attacks=(Attack("step", "gnss_pos", "north", 10.0, 25.0),))
    tlog = tmp_path / "north.tlog"
    run(sc, seed, tlog=str(tlog))
    return tlog


def test_a_replay_lists_what_it_said_in_order(tmp_path, capsys):
    """The summary lists each alarm (sensor, axis, offset, GNSS sample), clearance and WARNING by
    the log's clock, in the order the core said them: a 10 m north step on a simulated drive, its
    alarm at the report's sample; past LINES, how many more. A reboot's time goes back: the order is
    still the core's."""
    import json
    from guard.model.events import Alarm, Notice
    from guard.model.sensors import Sensor
    from guard.sinks.timeline import LINES, Timeline
    tlog = north_step(tmp_path, 4)
    assert main(["replay", str(tlog), "--report", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out.splitlines()
    report = json.loads((tmp_path / "r.json").read_text())
    first = report["alarms"][0]
    listed = [line for line in out if " s  ALARM " in line]
    assert len(listed) == len(report["alarms"]) and f"(GNSS sample {first['gnss_index']}" in listed[0], out
    assert "ALARM gnss_pos north +" in listed[0] and listed[0].strip().startswith(f"{first['time_usec'] / 1e6:.1f} s")
    alarm = Alarm(100_000_000, 1000, Sensor.GNSS_POS, "north", 30.0, 20.0, 10.0, "cusum")
    t = Timeline()
    t.on_events([alarm, Notice(2_000_000, "warning", "time jumped -98.0 s: filter re-initialised")])
    t.on_events([alarm] * LINES)
    lines = t.said()
    assert "ALARM gnss_pos north +10 m (GNSS sample 1000)" in lines[0] and "time jumped" in lines[1], lines
    assert len(lines) == LINES + 1 and lines[-1].startswith("... and 2 more"), lines[-1]


def test_a_replay_says_apart_how_far_the_estimate_stood_from_the_fixes_an_alarm_excluded(tmp_path, capsys):
    """A 10 m north step from 25 s to the end of a simulated drive: after its alarm the estimate is held
    by the IMU and the GNSS velocity, 10 m from the fixes on purpose. The summary says the fused fixes'
    distance and the excluded ones' apart; the report has both, and they add up to all."""
    import json
    tlog = north_step(tmp_path, 5)
    assert main(["replay", str(tlog), "--report", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out.splitlines()
    gap = json.loads((tmp_path / "r.json").read_text())["estimate_to_fix_m"]
    fused, out_ = gap["fused"], gap["excluded"]
    assert fused["fixes"] + out_["fixes"] == gap["fixes"] and out_["fixes"] >= 50, gap
    assert fused["max"] < 3.0 and 7.0 < out_["mean"] < 13.0 and gap["max"] == max(fused["max"], out_["max"]), gap
    said = [line.strip() for line in out if "whose position an alarm had excluded" in line]
    assert len(said) == 1 and said[0].startswith(f"at the {fused['fixes']} fixes fused, {fused['mean']:.1f} m"), out
