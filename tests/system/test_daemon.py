"""`guard run`, the daemon: end to end against the simulator, link faults, signals, systemd, signing, config.

Two ways to drive it. As real processes (`guard run` and `guard sim`, or `guard run` and a pymavlink peer in
this process), for what only a process shows: exit status, signals, stdout, the notify socket. In-process
(`Daemon(...).serve()` in a thread, a pymavlink peer on UDP loopback), for the fault cases: the test then
waits until the daemon has taken every sample it was sent (`d.samples`), so nothing depends on timing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

os.environ["MAVLINK20"] = "1"      # before pymavlink is imported, or frames are MAVLink 1 and never signed

import pytest                                          # noqa: E402
from foxglove_schemas_protobuf.Log_pb2 import Log      # noqa: E402
from mcap.reader import make_reader                    # noqa: E402
from pymavlink import mavutil                          # noqa: E402

from guard.config import parse                         # noqa: E402
from guard.runtime.agreement import LIVE_MIN_PAIRS, WANDER_SAY_MPS2, LiveWander     # noqa: E402
from guard.runtime.daemon import Daemon                        # noqa: E402
from guard.runtime.deviation import LiveCheck                  # noqa: E402
import guard.runtime.position_wander as position_wander          # noqa: E402
from guard_sim import scenario                               # noqa: E402
from guard_sim.mavout import Encoder                         # noqa: E402
from guard_sim.run import Simulation                         # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "configs" / "scenarios"
MAGIC = b"\x89MCAP0\r\n"
SAMPLE_TYPES = {"GPS_RAW_INT", "RAW_IMU", "ATTITUDE", "HEARTBEAT"}
CRITICAL, WARNING, NOTICE = 2, 4, 5
MAV_TYPE_ONBOARD_CONTROLLER = 18
GUARD_COMPONENT = 191


# --- helpers --------------------------------------------------------------------------------------------

def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(condition, timeout_s: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def scenario_messages(name, seed: int = 1, until_s: float | None = None, edit=None):
    """The simulator's messages as (t_us, msg), unpacked so that a test can change them first.

    `name`: a scenario's, or a Scenario. `edit(t_us, msg)` may change msg in place, or return False to drop it.
    """
    sim = Simulation(scenario.load(name) if isinstance(name, str) else name, seed)
    items = []
    for t_us, msgs in sim.ticks():
        if until_s is not None and t_us > until_s * 1e6:
            break
        for msg in msgs:
            if edit is None or edit(t_us, msg) is not False:
                items.append((t_us, msg))
    return sim.encoder, items


def frames(encoder, items) -> list[tuple[bytes, bool]]:
    """Packed (bytes, carries a sample) pairs, with the simulator's own (unsigned) sequence numbers."""
    return [(encoder.pack(msg), msg.get_type() in SAMPLE_TYPES) for _, msg in items]


def feed(peer, stream: list[tuple[bytes, bool]], d: Daemon | None = None, pace_every: int = 20) -> int:
    """Send the frames; in-process (`d` given) keep the daemon at most ~50 samples behind, then wait for all.

    Returns how many sample-carrying frames were sent. Without `d` (a daemon in another process) the pace is
    one millisecond per `pace_every` frames.
    """
    base = d.samples if d is not None else 0
    sent = 0
    for i, (buf, is_sample) in enumerate(stream, 1):
        peer.write(buf)
        sent += is_sample
        if i % pace_every == 0:
            time.sleep(0.001)
            if d is not None:
                wait_for(lambda: d.samples >= base + sent - 50, what=f"the daemon to take sample {sent}")
    if d is not None:
        wait_for(lambda: d.samples >= base + sent, what=f"the daemon to take all {sent} samples")
    return sent


def drain(peer, quiet_s: float = 0.4, max_s: float = 5.0) -> list:
    """Everything the peer received until nothing came for quiet_s."""
    got = []
    deadline = time.monotonic() + max_s
    while time.monotonic() < deadline:
        msg = peer.recv_match(blocking=True, timeout=quiet_s)
        if msg is None:
            break
        if msg.get_type() != "BAD_DATA":
            got.append(msg)
    return got


def texts(msgs, severity: int | None = None) -> list[str]:
    return [m.text for m in msgs if m.get_type() == "STATUSTEXT" and (severity is None or m.severity == severity)]


def connect_peer(port: int, key: bytes | None = None):
    peer = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1,
                                      dialect="ardupilotmega")
    if key is not None:
        peer.setup_signing(key, sign_outgoing=True)
    return peer


@contextlib.contextmanager
def in_process(cfg_dict: dict | None = None, mcap: str | None = None):
    """A Daemon serving udpin on a free loopback port in a thread; `connect()` makes a peer for it."""
    port = free_udp_port()
    out: list[str] = []
    d = Daemon(parse(cfg_dict or {}), connect=f"udpin:127.0.0.1:{port}", mcap=mcap, out=out.append)
    failure: list[BaseException] = []

    def serve() -> None:
        try:
            d.serve()
        except BaseException as e:     # noqa: BLE001 - handed to the test below
            failure.append(e)

    thread = threading.Thread(target=serve, name="guard-daemon", daemon=True)
    thread.start()
    wait_for(lambda: any("listening on" in line for line in out) or not thread.is_alive(), what="the daemon")
    peers = []

    def connect(key: bytes | None = None):
        peers.append(connect_peer(port, key))
        return peers[-1]

    try:
        yield SimpleNamespace(d=d, out=out, port=port, thread=thread, connect=connect)
    finally:
        d.should_exit = True
        thread.join(10)
        for p in peers:
            p.close()
    assert not thread.is_alive(), "the daemon did not stop within 10 s of should_exit"
    if failure:
        raise failure[0]


def read_mcap(path: Path):
    """(summary, {topic: [(schema name, data)]}) of a finished MCAP file."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        by_topic: dict[str, list] = {}
        for schema, channel, message in reader.iter_messages():
            by_topic.setdefault(channel.topic, []).append((schema.name if schema else "", message.data))
    return summary, by_topic


class Proc:
    """A `guard` subprocess whose stdout and stderr are collected line by line as they come."""

    def __init__(self, *args: str, env: dict | None = None):
        self.p = subprocess.Popen([sys.executable, "-m", "guard", *args], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                  env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self._threads = [threading.Thread(target=self._collect, args=(s, lines), daemon=True)
                         for s, lines in ((self.p.stdout, self.stdout), (self.p.stderr, self.stderr))]
        for t in self._threads:
            t.start()

    @staticmethod
    def _collect(stream, lines: list[str]) -> None:
        for line in stream:
            lines.append(line.rstrip("\n"))

    def wait_line(self, text: str, timeout_s: float = 20.0) -> None:
        wait_for(lambda: any(text in line for line in self.stdout) or self.p.poll() is not None, timeout_s,
                 f"{text!r} from guard")
        assert any(text in line for line in self.stdout), (self.stdout, self.stderr)

    def wait(self, timeout_s: float = 30.0) -> int:
        try:
            rc = self.p.wait(timeout_s)
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait()
        for t in self._threads:
            t.join(5)
        for stream in (self.p.stdout, self.p.stderr):   # read to the end by now: closed, not left to the collector
            stream.close()
        return rc

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
        self.wait(10)


@pytest.fixture
def procs():
    """Every Proc started by a test is killed at its end, whatever happened."""
    started: list[Proc] = []

    def start(*args: str, env: dict | None = None) -> Proc:
        started.append(Proc(*args, env=env))
        return started[-1]

    yield start
    for p in started:
        p.kill()


def start_daemon(procs, tmp_path: Path, *extra: str, env: dict | None = None) -> tuple[Proc, int]:
    port = free_udp_port()
    daemon = procs("run", "--connect", f"udpin:127.0.0.1:{port}", *extra, env=env)
    daemon.wait_line("listening on")
    return daemon, port


# --- 1. end to end: two processes ---------------------------------------------------------------------------

def alarm_indices(lines: list[str]) -> list[int]:
    return [int(m.group(1)) for line in lines if "CRITICAL" in line and (m := re.search(r"k=(\d+)", line))]


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])     # RAW_IMU; HIGHRES_IMU, as PX4's onboard link
def test_paper_attack_end_to_end(procs, tmp_path, autopilot):
    mcap_path = tmp_path / "run.mcap"
    daemon, port = start_daemon(procs, tmp_path, "--mcap", str(mcap_path))
    sim = procs("sim", "--scenario", "paper", "--seed", "7", "--out", f"udpout:127.0.0.1:{port}", "--speedup", "10",
                "--autopilot", autopilot)
    assert sim.wait(60) == 0, sim.stderr

    critical = [line for line in sim.stdout if line.startswith("[ground station] CRITICAL:")]
    assert critical, f"no CRITICAL STATUSTEXT reached the ground station: {sim.stdout}"
    ks = alarm_indices(critical)
    assert len(ks) == len(critical), critical
    assert 400 <= ks[0] <= 403, f"first alarm at GNSS sample {ks[0]}, the attack starts at 400"
    assert min(ks) >= 400, f"CRITICAL before the attack: {critical}"
    assert "GUARD ALARM gnss_pos north" in critical[0]

    daemon.p.send_signal(signal.SIGTERM)
    assert daemon.wait(15) == 0, daemon.stderr
    stopped = [line for line in daemon.stdout if "stopped after" in line]
    samples = int(re.search(r"stopped after (\d+) samples", stopped[-1]).group(1))
    assert samples >= 0.95 * 2 * 801, f"the daemon saw {samples} samples of 801 fixes and 801 IMU samples"
    summary, topics = read_mcap(mcap_path)
    assert summary is not None and summary.statistics.message_count > 0
    alarms = [json.loads(data) for _, data in topics.get("/alarms", [])]
    raised = [a for a in alarms if a["kind"] == "alarm"]
    assert raised and 400 <= raised[0]["gnss_index"] <= 403, alarms
    assert raised[0]["sensor"] == "gnss_pos" and raised[0]["channel"] == "north"
    logs = topics.get("/log", [])
    assert logs and {schema for schema, _ in logs} == {"foxglove.Log"}
    records = [Log.FromString(data) for _, data in logs]
    assert any(r.level == Log.ERROR and "ALARM" in r.message for r in records), records


def paper_at_1_hz(procs, tmp_path: Path, autopilot: str, ask: bool) -> tuple[list[str], list[str]]:
    """The paper's run from an autopilot whose port sends GPS_RAW_INT and the IMU at 1 Hz until asked
    for more: what the simulator printed, and what the daemon did (link.request_rates = ask)."""
    config = tmp_path / f"ask-{ask}.toml"
    config.write_text(f"[link]\nrequest_rates = {str(ask).lower()}\n")
    daemon, port = start_daemon(procs, tmp_path, "--config", str(config))
    sim = procs("sim", "--scenario", "paper", "--seed", "2", "--out", f"udpout:127.0.0.1:{port}", "--speedup", "10",
                "--stream-hz", "1", "--autopilot", autopilot)
    assert sim.wait(60) == 0, sim.stderr
    daemon.p.send_signal(signal.SIGTERM)
    assert daemon.wait(15) == 0, daemon.stderr
    return sim.stdout, daemon.stdout + daemon.stderr


@pytest.mark.parametrize("autopilot, imu", [("ardupilot", "RAW_IMU"), ("px4", "HIGHRES_IMU")])
def test_an_autopilot_streaming_at_1_hz_is_asked_for_more(procs, tmp_path, autopilot, imu):
    """guard asks for more (MAV_CMD_SET_MESSAGE_INTERVAL), the simulator honours it and acknowledges,
    and guard integrates the IMU from then on; the paper's attack at 40 s is caught at 40 s."""
    sim_out, daemon_out = paper_at_1_hz(procs, tmp_path, autopilot, ask=True)
    assert f"[autopilot] {imu} at 50 Hz, as asked" in sim_out, sim_out
    assert "[autopilot] GPS_RAW_INT at 10 Hz, as asked" in sim_out, sim_out
    assert any("IMU now at 10.0 Hz: integrated" in line for line in daemon_out), daemon_out
    assert any(f"asked the autopilot (system 1) for {imu} at 50 Hz" in line for line in daemon_out), daemon_out
    alarm = next(line for line in daemon_out if "GUARD ALARM" in line)
    assert "gnss_pos north" in alarm and re.search(r"t=40\.\d\d s", alarm), alarm


def test_with_request_rates_off_nothing_is_asked(procs, tmp_path):
    """The control: nothing asked, the IMU stays at 1 Hz and is not integrated."""
    sim_out, daemon_out = paper_at_1_hz(procs, tmp_path, "ardupilot", ask=False)
    assert not any(line.startswith("[autopilot]") for line in sim_out), sim_out
    assert not any("IMU now at" in line for line in daemon_out), daemon_out
    stopped = next(line for line in daemon_out if "stopped after" in line)
    assert "'imu_too_slow'" in stopped, stopped


def test_clean_run_end_to_end_no_alarm(procs, tmp_path):
    text = (SCENARIOS / "clean.toml").read_text()
    text, n = re.subn(r"(?m)^duration_s\s*=.*$", "duration_s = 90.0", text)
    assert n == 1
    clean = tmp_path / "clean90.toml"
    clean.write_text(text)
    daemon, port = start_daemon(procs, tmp_path)
    sim = procs("sim", "--scenario", str(clean), "--seed", "3", "--out", f"udpout:127.0.0.1:{port}",
                "--speedup", "15")
    assert sim.wait(60) == 0, sim.stderr
    assert not [line for line in sim.stdout if "CRITICAL" in line], sim.stdout

    daemon.p.send_signal(signal.SIGTERM)
    assert daemon.wait(15) == 0, daemon.stderr
    stopped = [line for line in daemon.stdout if "stopped after" in line]
    assert stopped, daemon.stdout
    samples = int(re.search(r"stopped after (\d+) samples, (\d+) alarm", stopped[-1]).group(1))
    expected = 90 * (50 + 10) + 2       # IMU 50 Hz, GNSS 10 Hz, both at t = 0 and t = 90 s
    assert samples >= 0.95 * expected, f"the daemon saw only {samples} of {expected} samples"
    assert " 0 alarm(s)" in stopped[-1]


# --- 2. what the daemon says on the link ------------------------------------------------------------------

def test_heartbeat_and_statistic_reach_the_peer():
    with in_process() as g:
        peer = g.connect()
        enc, items = scenario_messages("paper", until_s=45)   # through the attack at 40 s
        feed(peer, frames(enc, items), g.d)
        time.sleep(1.2)                   # one more heartbeat period, two statistic periods
        got = drain(peer)
    beats = [m for m in got if m.get_type() == "HEARTBEAT"]
    assert beats, [m.get_type() for m in got]
    for hb in beats:
        assert hb.get_srcComponent() == GUARD_COMPONENT and hb.get_srcSystem() == 1
        assert hb.type == MAV_TYPE_ONBOARD_CONTROLLER
        assert hb.autopilot == mavutil.mavlink.MAV_AUTOPILOT_INVALID
    ratios = [m for m in got if m.get_type() == "NAMED_VALUE_FLOAT"]
    assert len(ratios) >= 2 and {m.name for m in ratios} == {"grd_ratio"}
    assert all(m.get_srcComponent() == GUARD_COMPONENT for m in ratios)
    values = [m.value for m in ratios]
    assert all(math.isfinite(v) and v >= 0 for v in values), values
    stamps = [m.time_boot_ms for m in ratios]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps), stamps
    assert texts(got, CRITICAL) and texts(got, CRITICAL)[0].startswith("GUARD ALARM gnss_pos north")


def test_statistic_shows_the_threshold_crossing():
    with in_process() as g:
        peer = g.connect()
        enc, items = scenario_messages("paper", until_s=45)
        feed(peer, frames(enc, items), g.d)
        assert g.d.alarms >= 1
        time.sleep(1.2)
        got = drain(peer)
    values = [m.value for m in got if m.get_type() == "NAMED_VALUE_FLOAT"]
    assert max(values) >= 1.0, f"an alarm was raised, the statistic never showed it: {values}"


# --- 3. faults, in-process ---------------------------------------------------------------------------------

def test_garbage_and_bad_crc_are_counted_and_skipped():
    enc, items = scenario_messages("paper", until_s=20)
    stream, good = [], 0
    n_garbage = n_bad_crc = n_mixed = 0
    junk = bytes(b for b in range(256) if b not in (0xFD, 0xFE)) * 2     # no start byte: cannot swallow a frame
    for i, (buf, is_sample) in enumerate(frames(enc, items)):
        if i % 7 == 3:                      # a corrupt copy of this frame first: last CRC byte flipped
            bad = bytearray(buf)
            bad[-1] ^= 0x5A
            stream.append((bytes(bad), False))
            n_bad_crc += 1
        if i % 11 == 5:                     # a datagram of garbage
            stream.append((junk[i % 97:i % 97 + 40], False))
            n_garbage += 1
        if i % 13 == 8:                     # garbage and a valid frame in one datagram
            buf = junk[:25] + buf
            n_mixed += 1
        stream.append((buf, is_sample))
        good += is_sample
    with in_process() as g:
        peer = g.connect()
        feed(peer, stream, g.d)
        time.sleep(0.3)
        assert g.thread.is_alive()
        assert g.d.samples == good, "every valid sample is processed, none is lost to the garbage around it"
        skipped = dict(g.d.link.skipped)
        g.d.should_exit = True
        g.thread.join(10)
        summary = g.out[-1]
    # pymavlink reports one BAD_DATA per run of bad bytes: each bad-CRC frame is one, each garbage datagram is
    # one, but garbage that meets garbage (a garbage datagram, then one with a garbage prefix) may become one
    assert n_bad_crc + n_garbage <= skipped.get("bad_frame", 0) <= n_bad_crc + n_garbage + n_mixed, skipped
    assert "stopped after" in summary and f"'bad_frame': {skipped['bad_frame']}" in summary, summary


def test_gnss_fix_lost_mid_drive_warns_without_alarm():
    def no_fix(t_us, msg):
        if msg.get_type() == "GPS_RAW_INT" and 15e6 <= t_us < 20e6:     # 5 s without a 3D fix
            msg.fix_type, msg.lat, msg.lon = 1, 0, 0
    enc, items = scenario_messages("paper", until_s=35, edit=no_fix)   # the attack starts at 40 s
    with in_process() as g:
        peer = g.connect()
        n = feed(peer, frames(enc, items), g.d)
        got = drain(peer)
        assert g.d.samples == n
        assert g.d.monitor.skipped["gnss_no_fix"] == 50
        assert not g.d.monitor.gnss_lost, "the fix came back at 20 s"
    warnings = texts(got, WARNING)
    assert any("GNSS fix lost" in t for t in warnings), texts(got)
    assert not texts(got, CRITICAL), texts(got)
    assert g.d.alarms == 0


def test_link_silence_warns_and_recovers(caplog):
    caplog.set_level(logging.INFO)
    enc, items = scenario_messages("paper", until_s=15)
    stream = frames(enc, items)
    cut = next(i for i, (t_us, _) in enumerate(items) if t_us > 10e6)
    with in_process({"link": {"link_timeout_s": 0.5}}) as g:
        peer = g.connect()
        feed(peer, stream[:cut], g.d)
        time.sleep(1.5)
        assert g.thread.is_alive()
        n = feed(peer, stream[cut:], g.d)
        time.sleep(0.3)
        got = drain(peer)
        assert g.thread.is_alive()
    said = texts(got)
    silent = [i for i, t in enumerate(said) if "no GNSS or IMU data" in t]
    back = [i for i, t in enumerate(said) if "data is back" in t]
    assert silent and back and silent[0] < back[0], said
    assert len([i for i in silent if i < back[0]]) == 1, "warned once per silence"
    assert any("no GNSS or IMU data" in t for t in texts(got, WARNING)), "the silence is a WARNING"
    assert any("data is back" in t for t in texts(got, NOTICE)), "its end a NOTICE"
    assert n > 0 and not texts(got, CRITICAL)
    logged = [r.getMessage() for r in caplog.records]
    assert any("no GNSS or IMU data" in m for m in logged) and any("data is back" in m for m in logged), logged
    # the link stayed up during the silence: statistics kept coming between the two notices
    kinds = [(m.get_type(), getattr(m, "text", "")) for m in got]
    i0 = next(i for i, (k, t) in enumerate(kinds) if "no GNSS or IMU data" in t)
    i1 = next(i for i, (k, t) in enumerate(kinds) if "data is back" in t)
    assert any(k == "NAMED_VALUE_FLOAT" for k, _ in kinds[i0:i1]), kinds[i0:i1]


def test_link_silence_warning_states_the_timeout(caplog):
    with in_process({"link": {"link_timeout_s": 0.5}}):
        wait_for(lambda: any("no GNSS or IMU data" in r.getMessage() for r in caplog.records), 5)
    warning = next(r.getMessage() for r in caplog.records if "no GNSS or IMU data" in r.getMessage())
    assert "0.5 s" in warning, warning


def test_a_link_with_heartbeats_alone_is_silent(caplog):
    """An autopilot whose GNSS and IMU streams are off still sends HEARTBEAT: that is no data."""
    with in_process({"link": {"link_timeout_s": 1.0}}) as g:
        peer = g.connect()
        for _ in range(25):           # 10 Hz for 2.5 s: before, each one reset the silence clock
            peer.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GROUND_ROVER, mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                    0, 0, 0)
            time.sleep(0.1)
        got = drain(peer)
        assert g.d.samples >= 20, "the heartbeats reached the daemon"
    assert any("no GNSS or IMU data" in t for t in texts(got, WARNING)), texts(got)


def test_time_jumping_back_reinitialises_without_alarm():
    def back_5s(t_us, msg):
        if t_us >= 15e6 and hasattr(msg, "time_usec"):
            msg.time_usec -= 5_000_000
    enc, items = scenario_messages("paper", until_s=30, edit=back_5s)
    with in_process() as g:
        peer = g.connect()
        n = feed(peer, frames(enc, items), g.d)
        got = drain(peer)
        assert g.d.samples == n
        assert g.d.monitor.ekf is not None, "the filter started again on the next fix"
    notices = texts(got, WARNING)
    # the first shifted sample (15.0 s -> 10.0 s) comes 0.1 s after the last good one (14.9 s)
    assert any(re.search(r"time jumped -4\.9 s: filter re-initialised", t) for t in notices), notices
    assert not texts(got, CRITICAL) and g.d.alarms == 0


def test_a_log_directory_lost_in_flight_still_alarms(tmp_path):
    """The log's directory goes (a card pulled, a mount gone) after the daemon started: the next file
    (rotation every 10 s of vehicle time) cannot open. The log is said lost; the alarm still goes out.
    (A directory that cannot be written at start is an error before the link opens: test_operator.)"""
    logs = tmp_path / "logs"
    logs.mkdir()
    enc, items = scenario_messages("paper", until_s=45)
    with in_process({"log": {"rotate_s": 10.0}}, mcap=str(logs / "run.mcap")) as g:
        peer = g.connect()
        logs.rename(tmp_path / "gone")
        logs.write_text("a regular file now, so nothing can be created under it\n")
        feed(peer, frames(enc, items), g.d)
        got = drain(peer)
        assert g.thread.is_alive()
    critical = texts(got, CRITICAL)
    assert critical and re.search(r"GUARD ALARM gnss_pos north \+1\d\.\dm k=40[0-3]", critical[0]), critical
    assert any("MCAP log lost" in t for t in texts(got, WARNING)), texts(got)
    assert any("GUARD ALARM" in line for line in g.out)
    assert "MCAP errors" in g.out[-1], g.out[-1]


def test_alarm_not_lost_to_statustext_rate_limit():
    """GNSS jamming (the fix flapping) just before a spoof: four 'fix lost' warnings, then the alarm."""
    def flap(t_us, msg):
        if msg.get_type() == "GPS_RAW_INT" and t_us in (39.2e6, 39.4e6, 39.6e6, 39.8e6):
            msg.fix_type = 1
    enc, items = scenario_messages("paper", until_s=42, edit=flap)
    with in_process() as g:
        peer = g.connect()
        feed(peer, frames(enc, items), g.d)
        got = drain(peer)
        assert g.d.alarms >= 1
    assert texts(got, CRITICAL), (texts(got), dict(g.d.link.skipped))


def test_a_line_said_once_waits_for_the_rate_limit_rather_than_being_dropped():
    """Warnings beyond four a second are dropped and counted; a line said once (the compass's, below)
    is kept and goes out when the limit allows, whole."""
    with in_process() as g:
        peer = g.connect()
        feed(peer, frames(*scenario_messages("paper", until_s=1)), g.d)
        for i in range(4):
            g.d._operator(f"filler {i}")
        g.d._operator("a long line said once, which a ground station gets in two chunks at most", keep=True)
        g.d._operator("one more, dropped")
        time.sleep(1.5)                             # the loop ticks on, and the limit opens
        got = drain(peer)
    said = texts(got, WARNING)
    assert [t for t in said if t.startswith("GUARD filler")] == [f"GUARD filler {i}" for i in range(4)], said
    assert "".join(t for t in said if not t.startswith("GUARD filler")) == \
        "GUARD a long line said once, which a ground station gets in two chunks at most", said
    assert g.d.link.skipped["statustext_rate_limited"] == 1


def test_a_line_kept_through_the_rate_limit_goes_out_at_shutdown():
    with in_process() as g:
        peer = g.connect()
        feed(peer, frames(*scenario_messages("paper", until_s=1)), g.d)
        for i in range(4):
            g.d._operator(f"filler {i}")
        g.d._operator("kept, then the daemon stops", keep=True)
        g.d.should_exit = True                      # within the second the limit holds it
        g.thread.join(10)
        got = drain(peer)
    assert "GUARD kept, then the daemon stops" in texts(got, WARNING), texts(got)


def test_operator_lines_are_not_held_back_on_a_pipe():
    port = free_udp_port()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    p = subprocess.Popen([sys.executable, "-m", "guard", "run", "--connect", f"udpin:127.0.0.1:{port}"],
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=ROOT, env=env)
    try:
        ready, _, _ = select.select([p.stdout], [], [], 4.0)
        line = p.stdout.readline().decode() if ready else ""
    finally:
        p.kill()
        p.wait()
        p.stdout.close()
    assert "listening on" in line


# --- 4. signals on a real process ---------------------------------------------------------------------------

def run_and_stop(procs, tmp_path: Path, name: str, sig: int, seconds: int, *extra: str) -> Path:
    """A daemon logging to NAME.mcap gets `seconds` of the paper drive, then the signal.

    The last GNSS message has no fix: the daemon's 'GNSS fix lost' answer says it has taken everything.
    """
    mcap = tmp_path / f"{name}.mcap"
    daemon, port = start_daemon(procs, tmp_path, "--mcap", str(mcap), *extra)
    peer = connect_peer(port)

    def last_without_fix(t_us, msg):
        if msg.get_type() == "GPS_RAW_INT" and t_us == seconds * 1_000_000:
            msg.fix_type = 0
    try:
        enc, items = scenario_messages("paper", until_s=seconds, edit=last_without_fix)
        stream = frames(enc, items)
        feed(peer, stream, pace_every=1)
        deadline, got = time.monotonic() + 30, []
        while time.monotonic() < deadline and not any("GNSS fix lost" in t for t in texts(got)):
            got += drain(peer, quiet_s=0.5, max_s=1.0)
        assert any("GNSS fix lost" in t for t in texts(got)), "the daemon did not take the whole drive"
    finally:
        peer.close()
    daemon.p.send_signal(sig)
    rc = daemon.wait(15)
    if sig == signal.SIGKILL:
        assert rc == -signal.SIGKILL
    else:
        assert rc == 0, (rc, daemon.stderr)
        stopped = [line for line in daemon.stdout if "stopped after" in line]
        assert stopped and f"stopped after {sum(carries for _, carries in stream)} samples" in stopped[-1], \
            daemon.stdout
    return mcap


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_finishes_the_log(procs, tmp_path, sig):
    mcap = run_and_stop(procs, tmp_path, "run", sig, 10)
    assert mcap.read_bytes().endswith(MAGIC)
    summary, topics = read_mcap(mcap)
    assert summary is not None
    assert summary.statistics.message_count == sum(len(v) for v in topics.values()) > 0
    assert "/gnss/fix" in topics and "/estimate/state" in topics


def test_sigkill_then_mcap_recover(procs, tmp_path):
    config = tmp_path / "guard.toml"
    config.write_text("[log]\nchunk_kb = 16\n")
    clean = run_and_stop(procs, tmp_path, "clean", signal.SIGTERM, 20, "--config", str(config))
    clean_summary, _ = read_mcap(clean)
    reference = clean_summary.statistics.message_count
    assert reference > 1000

    cut = run_and_stop(procs, tmp_path, "cut", signal.SIGKILL, 20, "--config", str(config))
    data = cut.read_bytes()
    assert data.startswith(MAGIC) and not data.endswith(MAGIC), "a killed daemon cannot have finished the file"

    fixed = tmp_path / "fixed.mcap"
    rec = subprocess.run([sys.executable, "-m", "guard", "mcap-recover", str(cut), str(fixed)],
                         capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert rec.returncode == 0, rec.stderr
    summary, topics = read_mcap(fixed)
    assert summary is not None
    recovered = sum(len(v) for v in topics.values())
    assert summary.statistics.message_count == recovered
    assert recovered >= 0.8 * reference, f"recovered {recovered} of the {reference} a clean run logs"
    assert f"recovered {recovered} messages" in rec.stdout, rec.stdout
    assert "/gnss/fix" in topics and "/estimate/state" in topics


# --- 5. systemd notify -------------------------------------------------------------------------------------

def test_systemd_notify(procs, tmp_path):
    path = tmp_path / "n.sock"
    if len(str(path)) > 100:            # AF_UNIX paths are limited to 108 bytes
        path = Path(f"/tmp/guard-test-{os.getpid()}.sock")
    with contextlib.closing(socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)) as sock:
        sock.bind(str(path))
        sock.settimeout(0.2)
        port = free_udp_port()
        daemon = procs("run", "--connect", f"udpin:127.0.0.1:{port}",
                       env={"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "1000000"})
        got: list[tuple[float, str]] = []

        def receive_until(pred, timeout_s: float) -> None:
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline and not pred():
                with contextlib.suppress(socket.timeout):
                    got.append((time.monotonic(), sock.recv(4096).decode()))

        receive_until(lambda: any("READY=1" in m for _, m in got), 20)
        ready = [(t, m) for t, m in got if "READY=1" in m]
        assert ready, (got, daemon.stderr)
        # the link is up when READY=1 is sent: the daemon already holds its UDP port
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe, pytest.raises(OSError):
            probe.bind(("127.0.0.1", port))
        t_ready = ready[0][0]
        receive_until(lambda: time.monotonic() > t_ready + 2.0, 2.5)
        pings = [t for t, m in got if "WATCHDOG=1" in m.split("\n")]
        assert any(t <= t_ready + 2.0 for t in pings), got
        assert len(pings) >= 2 and max(b - a for a, b in zip(pings, pings[1:])) < 1.0, \
            f"WATCHDOG_USEC=1 s needs a ping more often than once a second: {pings}"
        assert not any("STOPPING=1" in m for _, m in got)

        daemon.p.send_signal(signal.SIGTERM)
        receive_until(lambda: any("STOPPING=1" in m for _, m in got), 10)
        assert any("STOPPING=1" in m for _, m in got), got
        assert daemon.wait(15) == 0
    with contextlib.suppress(OSError):
        path.unlink()


# --- 6. signing --------------------------------------------------------------------------------------------

def test_signing_required(tmp_path):
    key = bytes(range(1, 33))
    key_file = tmp_path / "signing.key"
    key_file.write_bytes(key)
    cfg = {"link": {"signing_key_file": str(key_file), "require_signed": True}}
    enc, items = scenario_messages("paper", until_s=5)
    with in_process(cfg) as g:
        unsigned = g.connect()
        feed(unsigned, frames(enc, items))
        wait_for(lambda: g.d.link.skipped["bad_signature"] == len(items), 5, what="every frame rejected")
        time.sleep(0.2)
        assert g.d.samples == 0, "unsigned frames must not be processed"

        signed = g.connect(key)
        enc2, items2 = scenario_messages("paper", seed=2, until_s=5)
        stream = []
        for _, msg in items2:               # packed by the peer's own MAVLink: signed with its key
            stream.append((bytes(msg.pack(signed.mav)), msg.get_type() in SAMPLE_TYPES))
            signed.mav.seq = (signed.mav.seq + 1) % 256
        assert all(buf[2] & 0x01 for buf, _ in stream), "the peer signs"
        n = feed(signed, stream, g.d)
        assert g.d.samples == n > 0
        assert g.d.link.skipped["bad_signature"] == len(items), "no signed frame was rejected"

        feed(signed, stream[:20])           # replayed: signed with the right key, but old time stamps
        wrong = g.connect(bytes(32))        # signed with another key
        feed(wrong, [(bytes(msg.pack(wrong.mav)), False) for _, msg in items2[:20]])
        wait_for(lambda: g.d.link.skipped["bad_signature"] == len(items) + 40, 5, what="40 more rejections")
        assert g.d.samples == n, "replayed or wrongly signed samples must not be processed"
        time.sleep(1.2)
        from_daemon = drain(signed)
    assert from_daemon, "the daemon answers the signed peer"
    for m in from_daemon:
        assert m.get_msgbuf()[2] & 0x01, f"{m.get_type()} sent unsigned"
        assert m._signed, f"{m.get_type()}: signature does not verify with the shared key"
    assert {"HEARTBEAT", "NAMED_VALUE_FLOAT"} <= {m.get_type() for m in from_daemon}


# --- 7. errors a user can fix ------------------------------------------------------------------------------

@pytest.mark.parametrize("body, key", [
    ("[link]\nheartbeat_hz = 1.0\nhartbeat_hz = 2.0\n", "link.hartbeat_hz"),
    ("[link]\nlink_timeout_s = \"five\"\n", "link.link_timeout_s"),
    ("[monitor]\nvehicle = \"boat\"\n", "monitor.vehicle"),
    ("[link]\nrequire_signed = true\n", "link.require_signed"),
    ("[detector]\nshock_sigma = 2.0\n", "detector.shock_sigma"),
], ids=["unknown-key", "wrong-type", "bad-choice", "signed-without-key", "shock-bound-below-a-shift"])
def test_config_error_is_one_line(tmp_path, body, key):
    bad = tmp_path / "bad.toml"
    bad.write_text(body)
    r = subprocess.run([sys.executable, "-m", "guard", "run", "--config", str(bad)], capture_output=True,
                       text=True, cwd=ROOT, timeout=30)
    assert r.returncode == 78, "EX_CONFIG: the systemd unit does not restart on it"
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert key in lines[0] and str(bad) in lines[0], lines[0]
    assert "listening on" not in r.stdout


def test_a_missing_config_is_a_config_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "guard", "run", "--config", str(tmp_path / "none.toml")],
                       capture_output=True, text=True, cwd=ROOT, timeout=30)
    assert r.returncode == 78 and "none.toml" in r.stderr, (r.returncode, r.stderr)


def test_tcp_nothing_listening_is_one_line():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:     # a port with nobody behind it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = subprocess.run([sys.executable, "-m", "guard", "run", "--connect", f"tcp:127.0.0.1:{port}"],
                       capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 1, "a link that may come back: not a config error, systemd restarts it"
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert f"tcp:127.0.0.1:{port}" in lines[0] and "refused" in lines[0].lower(), lines[0]
    assert "listening on" not in r.stdout


def test_shipped_config_is_the_defaults():
    """configs/guard.toml documents every key with its default: it must say what the code does."""
    from guard.config import Config, load
    shipped = load(str(ROOT / "configs" / "guard.toml"))
    assert dataclasses.replace(shipped, source_text="") == Config()


def test_a_link_without_the_imu_stream_says_so(caplog):
    """GPS_RAW_INT at 10 Hz but no RAW_IMU (an autopilot whose raw-sensor stream is off): the warning
    names the missing stream, and only it."""
    enc, items = scenario_messages("paper", until_s=3)
    gps = [it for it in items if it[1].get_type() == "GPS_RAW_INT"]
    sent: list[float] = []
    got: list = []

    def listen_until(t_end: float) -> None:
        while (left := t_end - time.monotonic()) > 0:
            msg = peer.recv_match(blocking=True, timeout=left)
            if msg is not None and msg.get_type() != "BAD_DATA":
                got.append(msg)

    with in_process({"link": {"link_timeout_s": 0.5}}) as g:
        peer = g.connect()
        for buf, _ in frames(enc, gps[:20]):
            peer.write(buf)
            sent.append(time.monotonic())
            listen_until(sent[-1] + 0.1)
        # what came within 0.3 s of the last fix: the stream's end is silence only 0.5 s after it, so a
        # GNSS warning here would be about the stream itself
        listen_until(sent[-1] + 0.3)
        assert g.d.samples >= 15, "the fixes reached the daemon"
    warnings = texts(got, WARNING)
    assert any("no IMU data for 0.5 s" in t for t in warnings), texts(got)
    # in chunks, a ground station joins them: what to stream, for either autopilot
    assert "SRn_RAW_SENS; HIGHRES_IMU: PX4's onboard mode" in "".join(warnings), warnings
    # a loaded machine may hold this test's sender back past the timeout: the daemon is then right to
    # say the GNSS fell silent too; only when every fix went out in time must the warning spare it
    if max(b - a for a, b in zip(sent, sent[1:])) < 0.35:
        assert not any("GNSS" in t for t in warnings), warnings


def test_an_autopilot_of_another_system_id_is_named_when_the_data_falls_silent(caplog):
    """An autopilot whose SYSID_THISMAV is 7 while guard reads system 1: its fixes are skipped, and
    the silence warning names the system that sends them and the key to set."""
    _, items = scenario_messages("paper", until_s=2)
    enc7 = Encoder()
    enc7.mav.srcSystem = 7
    gps = [it for it in items if it[1].get_type() == "GPS_RAW_INT"]
    caplog.set_level(logging.WARNING)
    with in_process({"link": {"link_timeout_s": 0.5}}) as g:
        peer = g.connect()
        for _, msg in gps[:15]:
            peer.write(enc7.pack(msg))
            time.sleep(0.05)
        wait_for(lambda: any("system 7 sends GPS_RAW_INT" in r.getMessage() for r in caplog.records),
                 what="the silence warning naming system 7")
        assert g.d.samples == 0, "system 7 is not read: link.system_id is 1"
    said = [r.getMessage() for r in caplog.records if "system 7" in r.getMessage()]
    assert "no GNSS or IMU data" in said[0] and "--system-id or link.system_id" in said[0], said


def test_a_long_warning_reaches_the_ground_station_whole():
    """A STATUSTEXT holds 50 bytes; a longer warning goes in MAVLink 2 chunks (one id, chunk_seq 0,
    1, ...) that a ground station joins: here the one said before the receiver's first fix."""
    def no_fix_yet(t_us, msg):
        if msg.get_type() == "GPS_RAW_INT" and t_us < 1e6:
            msg.fix_type, msg.lat, msg.lon = 1, 0, 0
    enc, items = scenario_messages("paper", until_s=3, edit=no_fix_yet)
    with in_process() as g:
        peer = g.connect()
        feed(peer, frames(enc, items), g.d)
        got = drain(peer)
    chunks = [m for m in got if m.get_type() == "STATUSTEXT" and m.id != 0]
    assert [m.chunk_seq for m in chunks] == [0, 1] and len({m.id for m in chunks}) == 1, \
        [(m.id, m.chunk_seq, m.text) for m in chunks]
    assert len(chunks[0].text) == 50 and chunks[0].severity == chunks[1].severity == WARNING
    assert "".join(m.text for m in chunks) == "GUARD GNSS without a fix: monitoring starts at the first fix"
    assert all(len(t) <= 50 for t in texts(got))


@pytest.mark.parametrize("iron", [(0.15, -0.1), (0.0, 0.0)])
def test_a_compass_that_reads_off_by_heading_is_said_once_on_the_link(iron, caplog, monkeypatch):
    """A compass with a hard iron of 0.18 of the field (up to 10 degrees by heading) from the start, on
    the simulator's loop: the magnetometer alarms at its first turn, and once the turns show the iron
    (a lap, about two minutes) the ground station is told once, at WARNING, that the compass reads that
    far off by heading and that a field come in flight fits alike, with that first alarm's k. A clean
    compass: nothing said of it. The simulator's usual receiver: its position's wander measured (over
    2 minutes of fixes here, not 5, to keep the drive short) and not said."""
    monkeypatch.setattr(position_wander, "LIVE_MIN_SPAN_S", 120.0)
    base = scenario.load("clean")
    sc = dataclasses.replace(base, noise=dataclasses.replace(base.noise, mag_iron_x=iron[0], mag_iron_y=iron[1]))
    enc, items = scenario_messages(sc, seed=3, until_s=200)
    with caplog.at_level(logging.INFO), in_process() as g:
        peer = g.connect()
        feed(peer, frames(enc, items), g.d)
        got = drain(peer)
    chunks: dict[int, list] = {}
    for m in got:
        if m.get_type() == "STATUSTEXT" and m.id:
            chunks.setdefault(m.id, []).append(m)
    said = ["".join(m.text for m in sorted(c, key=lambda m: m.chunk_seq)) for c in chunks.values()]
    # the simulator's levelled accelerometers agree with its GNSS: their wander is measured, and not said
    wander = next(s for s in g.d.pump.sinks if isinstance(s, LiveWander))
    assert not wander.done and wander.checked[1] >= LIVE_MIN_PAIRS and wander.checked[0] < WANDER_SAY_MPS2 / 4, \
        wander.checked
    assert not any("accelerometers wander" in t for t in said)
    receiver = next(s for s in g.d.pump.sinks if isinstance(s, position_wander.LivePositionWander))
    assert not receiver.done and receiver.checked is not None and receiver.checked < position_wander.SAY_RATIO, \
        receiver.checked
    assert not any("position wanders" in t for t in said)
    said = [(t, c[0].severity) for t, c in zip(said, chunks.values()) if "compass reads" in t]
    logged = [r.getMessage() for r in caplog.records if "compass reads" in r.getMessage()]
    if iron == (0.0, 0.0):
        assert not said and not logged, (said, logged)
        check = next(s for s in g.d.pump.sinks if isinstance(s, LiveCheck))
        assert check.done and not check.stretches, "the turns showed a true compass: the check let go of its readings"
        return
    assert len(said) == 1 and said[0][1] == WARNING and len(logged) == 1, (said, logged)
    assert said[0][0] == "GUARD " + logged[0]
    size = float(re.search(r"up to (\d+) deg off by heading", logged[0]).group(1))
    assert abs(size - math.degrees(math.asin(math.hypot(*iron)))) <= 2.0, logged
    first = re.search(r"first alarm, k=(\d+)", logged[0])
    mags = [int(re.search(r"k=(\d+)", t).group(1)) for t in texts(got, CRITICAL) if "mag" in t]
    assert first and mags and int(first.group(1)) == mags[0], (logged, texts(got, CRITICAL))


def joined(msgs) -> list[tuple[str, int]]:
    """Each STATUSTEXT whole, its MAVLink 2 chunks joined, with its severity."""
    whole, chunks = [], {}
    for m in msgs:
        if m.get_type() != "STATUSTEXT":
            continue
        if m.id:
            chunks.setdefault(m.id, []).append(m)
        else:
            whole.append((m.text, m.severity))
    return whole + [("".join(m.text for m in sorted(c, key=lambda m: m.chunk_seq)), c[0].severity)
                    for c in chunks.values()]


def test_a_rough_vehicle_s_wandering_sensors_are_said_once_on_the_link(caplog, monkeypatch):
    """The simulator's forward and sideways accelerometers off by an error that changes every 8 s (a
    Gauss-Markov-like wander of 0.6 m/s^2, as a hard-flown copter's levelled accelerometers read): once
    enough adjacent 8 s windows show it (the second minute's check), the ground station is told once, at
    WARNING, with its size, that a bias of a few tenths is within what the vehicle does; the check then
    lets go of what it held. Its receiver's position wanders too (a Gauss-Markov error of 2 m over 20 s,
    as an older receiver's): once its fixes span enough time (2 minutes here, not 5, to keep the drive
    short) it is told once, at WARNING, that the position alarms may be the receiver's own. The clean
    drive beside the compass's test above measures both and says neither."""
    monkeypatch.setattr(position_wander, "LIVE_MIN_SPAN_S", 120.0)
    import random
    rng = random.Random(7)
    attacks = tuple(scenario.Attack("bias", "accel", axis, rng.gauss(0.0, 0.6), 8.0 * i, 8.0)
                    for i in range(25) for axis in ("x", "y"))
    base = scenario.load("clean")
    sc = dataclasses.replace(base, attacks=attacks, noise=dataclasses.replace(
        base.noise, gnss_pos_markov_m=2.0, gnss_pos_markov_tau_s=20.0))
    enc, items = scenario_messages(sc, seed=4, until_s=190)
    with caplog.at_level(logging.INFO), in_process() as g:
        peer = g.connect()
        feed(peer, frames(enc, items), g.d)
        got = drain(peer)
    said = [(t, sev) for t, sev in joined(got) if "accelerometers wander" in t]
    logged = [r.getMessage() for r in caplog.records if "accelerometers wander" in r.getMessage()]
    assert len(said) == 1 and said[0][1] == WARNING and len(logged) == 1, (said, logged)
    assert said[0][0] == "GUARD " + logged[0]
    size = float(re.search(r"wander ([0-9.]+) m/s\^2", logged[0]).group(1))
    # the Allan deviation of a vector whose axes each step by N(0, 0.6) every window: about 0.6 * sqrt(2)
    assert 0.5 <= size <= 1.3, logged
    wander = next(s for s in g.d.pump.sinks if isinstance(s, LiveWander))
    assert wander.done and not wander.segments and wander.checked[1] >= LIVE_MIN_PAIRS
    said = [(t, sev) for t, sev in joined(got) if "position wanders" in t]
    logged = [r.getMessage() for r in caplog.records if "position wanders" in r.getMessage()]
    assert len(said) == 1 and said[0][1] == WARNING and len(logged) == 1, (said, logged)
    assert said[0][0] == "GUARD " + logged[0] and "its position alarms may be its own" in logged[0]
    receiver = next(s for s in g.d.pump.sinks if isinstance(s, position_wander.LivePositionWander))
    assert receiver.done and receiver.checked > position_wander.SAY_RATIO and not len(receiver.rows)


def said_on_the_link(edit, phrase: str) -> tuple[list[tuple[str, int]], list]:
    """The paper scenario's first 30 s (its attack starts at 40 s), each message changed by `edit`,
    through the daemon in process: the (text, severity) of the STATUSTEXTs that hold `phrase`, and
    all it said."""
    enc, items = scenario_messages("paper", until_s=30, edit=edit)
    with in_process() as g:
        peer = g.connect()
        feed(peer, frames(enc, items), g.d)
        got = joined(drain(peer))
    return [(t, sev) for t, sev in got if phrase in t], got


def test_accelerometers_that_stop_reading_the_vehicle_are_said_on_the_link():
    """RAW_IMU's z axis reads 600 mG less from 10 s (a clipped or injected vertical axis): the
    ground station is told, once, at WARNING, that the accelerometers do not read the vehicle; the
    drive before it, and the same drive untouched, say nothing of it."""
    def clipped(t_us, msg):
        if msg.get_type() == "RAW_IMU" and t_us >= 10e6:
            msg.zacc += 600                 # mG: z is down, so the vehicle seems to fall at 5.9 m/s^2
    for edit, said in ((clipped, 1), (None, 0)):
        lines, got = said_on_the_link(edit, "upward over 4 s")
        assert len(lines) == said, got
        assert all(t.startswith("GUARD the accelerometers read the vehicle accelerating -5.") and sev == WARNING
                   for t, sev in lines), lines


def test_accelerometers_that_misread_gravity_at_rest_are_said_on_the_link():
    """A vehicle parked (the simulator's fixes held at its first position, speed 0; RAW_IMU reading
    gravity alone, the gyro still), its accelerometers reading 850 mG where 1 g is due: the ground
    station is told, once, at WARNING, with the figure; the same vehicle reading 1000 mG is not."""
    for z_mg, said in ((-850, 1), (-1000, 0)):
        first = {}

        def parked(t_us, msg, z_mg=z_mg, first=first):
            if msg.get_type() == "GPS_RAW_INT":
                if msg.fix_type >= 3:
                    first.setdefault("at", (msg.lat, msg.lon, msg.alt))
                    msg.lat, msg.lon, msg.alt = first["at"]
                msg.vel = 0
            elif msg.get_type() == "RAW_IMU":
                msg.xacc, msg.yacc, msg.zacc = 0, 0, z_mg
                msg.xgyro = msg.ygyro = msg.zgyro = 0
        lines, got = said_on_the_link(parked, "at rest over")
        assert len(lines) == said, got
        assert all(t.startswith("GUARD the accelerometers read 8.34 m/s^2 at rest") and sev == WARNING
                   for t, sev in lines), lines
