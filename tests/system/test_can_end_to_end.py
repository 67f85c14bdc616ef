"""CAN end to end: one simulated drive over MAVLink and over DroneCAN gives the same alarms.

Three ways in:
- In one process, on python-can's `virtual` interface: the simulator writes a tlog AND publishes the
  same samples as DroneCAN frames; a CanSource opened first gets every frame queued (the virtual bus
  keeps an unbounded queue per receiver), and is drained only after the whole drive was published,
  long after its transfer timeout and silence timeout (both on the monotonic clock) have run out.
  The tlog goes through `replay()`, the frames through a `Monitor`, both told the vehicle is a ground
  one: the tlog's HEARTBEAT says so, DroneCAN has no way to (`monitor.vehicle = "auto"` takes a
  vehicle it hears no HEARTBEAT from as an air vehicle, whose model differs).
- Between two processes, `guard sim --can` and `guard run --connect can:udp_multicast:...`, inside a
  network namespace made for the test (so no multicast leaves the machine): needs root, `ip` and
  msgpack, else skipped.
- A bus that cannot be opened: one line on stderr and a non-zero exit.

What may differ between the paths: DroneCAN RawIMU carries float16, MAVLink RAW_IMU integers in
mG and mrad/s, so the statistics differ slightly. Alarm times, indices, sensors and channels must not.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from guard.sources.can import CanSource
from guard.config import parse
from guard.core.monitor import Monitor
from guard.sources.tlog import TlogReader
from guard.model.events import Alarm
from guard.runtime.replay import replay
from guard.model.samples import GnssFix
from guard_sim import scenario
from guard_sim.canbus import CanPublisher
from guard_sim.run import run

ROOT = Path(__file__).resolve().parents[2]
# Not gyro_bias: its first alarm (mag yaw, on a slowly growing statistic) comes 1-2 GNSS samples apart on
# the two paths, the quantisation of the IMU differing (MAVLink integers, DroneCAN float16).
CASES = [("paper", 1), ("paper", 2), ("paper", 3), ("accel_bias", 1)]
GROUND = parse({"monitor": {"vehicle": "ground"}}, "test")      # the simulator drives a car
QUIET_S = 0.2           # a poll that waits this long for nothing: the bus's queue is empty

# --- one process, virtual bus -----------------------------------------------------------------------------

def drain(source: CanSource, monitor: Monitor) -> tuple[list[Alarm], list[int]]:
    """Poll until the bus has been empty for QUIET_S; the alarms raised and the GNSS samples' times.

    poll() also returns None for a frame that completes no sample (the first frames of a multi-frame
    transfer, a magnetometer reading), so only a poll that waited its whole timeout means "empty".
    """
    alarms, gnss_t_us = [], []
    while True:
        t0 = time.monotonic()
        sample = source.poll(QUIET_S)
        if sample is None:
            if time.monotonic() - t0 >= QUIET_S:
                return alarms, gnss_t_us
            continue
        if isinstance(sample, GnssFix):
            gnss_t_us.append(sample.t_us)
        alarms += [e for e in monitor.step(sample) if isinstance(e, Alarm)]


@pytest.fixture(scope="module", params=CASES, ids=[f"{name}-{seed}" for name, seed in CASES])
def both_paths(request, tmp_path_factory):
    name, seed = request.param
    tlog = tmp_path_factory.mktemp("can-e2e") / f"{name}-{seed}.tlog"
    url = f"can:virtual:e2e-{uuid.uuid4().hex[:8]}"
    with CanSource(url, gnss_node_id=None, imu_node_id=None) as source:    # first: it must be there to receive
        with CanPublisher(url) as publisher:
            truth = run(scenario.load(name), seed, tlog=str(tlog), can=publisher, fast=True)
        # the day the tlog says it was recorded, as its replay takes it (the magnetic declination's)
        with TlogReader(str(tlog)) as reader:
            date = reader.date
        alarms, gnss_t_us = drain(source, Monitor(GROUND.monitor, record_tests=False, date=date))
    return {"alarms": alarms, "gnss_t_us": gnss_t_us, "stats": source.stats, "messages": source.messages,
            "report": replay(str(tlog), GROUND), "tlog_gnss_t_us": truth["trajectory"]["t_usec"]}


def test_late_drain_decodes_every_transfer_and_alarms_alike(both_paths):
    """Every transfer published is decoded, however late; the first alarm has the same sensor and
    channel, within one GNSS sample (DroneCAN carries the IMU and the accuracies in float16, and guard
    measures the IMU's noise from its own samples: the two paths' noise models differ by that much).

    Times are compared on the tlog's clock: a CAN time base may start elsewhere (the last GNSS
    sample of both paths is the same sample, whatever happened to the first).
    """
    can, report = both_paths, both_paths["report"]
    tlog_messages = report["messages"]
    assert can["messages"] == {"uavcan.equipment.gnss.Fix2": tlog_messages["GPS_RAW_INT"],
                               "uavcan.equipment.ahrs.RawIMU": tlog_messages["RAW_IMU"],
                               "uavcan.equipment.ahrs.MagneticFieldStrength2": tlog_messages["RAW_IMU"]}
    for reason in ("bad_transfer", "unknown_type", "other_node", "other_sensor", "not_dronecan", "no_fix"):
        assert can["stats"][reason] == 0, (reason, can["stats"])
    assert can["stats"]["silent"] <= 2          # each sensor "silent" once: nothing was read while the sim ran
    assert report["alarms"] and can["alarms"], "attack missed on one path"
    first_tlog, first_can = report["alarms"][0], can["alarms"][0]
    can_to_tlog_us = can["tlog_gnss_t_us"][-1] - can["gnss_t_us"][-1]
    assert (first_can.sensor, first_can.channel) == (first_tlog["sensor"], first_tlog["channel"])
    gnss_period_us = (can["gnss_t_us"][-1] - can["gnss_t_us"][0]) / (len(can["gnss_t_us"]) - 1)
    assert abs(first_can.t_us + can_to_tlog_us - first_tlog["time_usec"]) <= 1.01 * gnss_period_us


def test_same_first_alarm_and_gnss_count_over_mavlink_and_can(both_paths):
    can, report = both_paths, both_paths["report"]
    assert len(can["gnss_t_us"]) == report["gnss_samples"]
    first_tlog, first_can = report["alarms"][0], can["alarms"][0]
    assert (first_can.sensor, first_can.channel) == (first_tlog["sensor"], first_tlog["channel"])
    assert abs(first_can.gnss_index - first_tlog["gnss_index"]) <= 1       # float16 on CAN: see above


# --- two processes, udp_multicast in a network namespace ---------------------------------------------------

GROUP = "239.74.163.2"
ALARM = re.compile(r"GUARD ALARM (\w+) (\w+) \S+ k=(\d+)")
STOPPED = re.compile(r"stopped after (\d+) samples")


def ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


class Lines:
    """A process's stdout collected line by line as it comes."""

    def __init__(self, p: subprocess.Popen):
        self.p, self.lines = p, []
        self._thread = threading.Thread(target=self._collect, daemon=True)
        self._thread.start()

    def _collect(self) -> None:
        for line in self.p.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, pattern: str, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.p.poll() is None:
            if any(re.search(pattern, line) for line in self.lines):
                return True
            time.sleep(0.05)
        return any(re.search(pattern, line) for line in self.lines)

    def join(self) -> None:
        self._thread.join(5)


@pytest.fixture(scope="module")
def multicast_run(tmp_path_factory):
    """`guard run` and `guard sim` (paper, seed 1) as two processes on can:udp_multicast in a fresh namespace.

    `guard sim --can` alone is not paced (sim/run.py run() paces only live MAVLink output, so
    --speedup is ignored): it publishes as fast as it can and the daemon's socket, 256 datagrams
    (one a frame) at the default 208 KiB receive buffer, overflows: samples are lost without trace
    and the alarm's k comes early. `--out` to a port nobody listens on inside the namespace makes
    the simulator pace its CAN output too. At --speedup 4 (450 frames/s) the buffer still covers a
    0.5 s stall of either process on a busy two-core machine; at 20x it did not.
    """
    if importlib.util.find_spec("msgpack") is None:
        pytest.skip("python-can's udp_multicast interface needs msgpack")
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) to make a network namespace")
    ns = f"guardtest-{uuid.uuid4().hex[:8]}"
    made = ip("netns", "add", ns)
    if made.returncode != 0:
        pytest.skip(f"cannot create a network namespace: {made.stderr.strip()}")
    daemon = stderr = None
    try:
        for args in (("link", "set", "lo", "up"), ("route", "add", "224.0.0.0/4", "dev", "lo")):
            r = ip("netns", "exec", ns, "ip", *args)
            if r.returncode != 0:
                pytest.skip(f"cannot set up multicast on lo in a namespace: ip {' '.join(args)}: {r.stderr.strip()}")
        work = tmp_path_factory.mktemp("can-mcast")
        config, errors = work / "guard.toml", work / "daemon.stderr"
        stderr = errors.open("w")
        config.write_text('[link]\nconnect = "udpout:127.0.0.1:14599"     # alarms also go out on MAVLink\n')
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        exec_ns = ["ip", "netns", "exec", ns, sys.executable, "-m", "guard"]   # ip execs: the pid is python's
        daemon = subprocess.Popen([*exec_ns, "run", "--connect", f"can:udp_multicast:{GROUP}", "--config",
                                   str(config)], stdout=subprocess.PIPE, stderr=stderr, text=True,
                                  cwd=ROOT, env=env)
        out = Lines(daemon)
        assert out.wait_for("listening on", 20), (out.lines, daemon.poll())
        sim = subprocess.run([*exec_ns, "sim", "--scenario", "paper", "--seed", "1", "--can",
                              f"can:udp_multicast:{GROUP}", "--out", "udpout:127.0.0.1:14598", "--speedup", "4"],
                             capture_output=True, text=True, cwd=ROOT, env=env, timeout=40)
        assert sim.returncode == 0, sim.stderr
        out.wait_for("GUARD ALARM", 5)
        time.sleep(0.5)                 # paced: the daemon is at most a few frames behind
        daemon.send_signal(signal.SIGINT)
        rc = daemon.wait(15)
        out.join()
        yield {"rc": rc, "stdout": out.lines, "stderr": errors.read_text()}
    finally:
        if daemon is not None and daemon.poll() is None:
            daemon.kill()
            daemon.wait()
        if daemon is not None:
            daemon.stdout.close()
        if stderr is not None:
            stderr.close()
        ip("netns", "del", ns)


def test_daemon_reads_can_from_another_process(multicast_run):
    r = multicast_run
    assert r["rc"] == 0, r["stderr"]
    alarms = [m.groups() for line in r["stdout"] if (m := ALARM.search(line))]
    assert alarms and alarms[0][:2] == ("gnss_pos", "north"), r["stdout"]
    (stopped,) = [int(m.group(1)) for line in r["stdout"] if (m := STOPPED.search(line))]
    assert stopped >= 1600, r["stdout"]                 # 801 GNSS + 801 IMU samples, none lost
    assert "bad_transfer" not in r["stdout"][-1], r["stdout"][-1]


def test_daemon_over_can_alarms_at_the_attack(multicast_run):
    alarms = [m.groups() for line in multicast_run["stdout"] if (m := ALARM.search(line))]
    sensor, channel, k = alarms[0]
    assert (sensor, channel) == ("gnss_pos", "north") and 400 <= int(k) <= 402, multicast_run["stdout"]


# --- a bus that cannot be opened --------------------------------------------------------------------------

OPEN_ERRORS = {
    "run-socketcan": (["run", "--connect", "can:socketcan:vcan0"], ("socketcan", "vcan0")),
    "sim-bogus": (["sim", "--can", "can:bogus:x", "--scenario", "paper"], ("bogus", "can:bogus:x")),
}
NO_PYSERIAL = importlib.util.find_spec("serial") is None


def guard_fails(args: list[str]) -> tuple[int, list[str]]:
    if os.path.exists("/sys/class/net/vcan0"):
        pytest.skip("this machine has a vcan0")
    r = subprocess.run([sys.executable, "-m", "guard", *args], capture_output=True, text=True, cwd=ROOT,
                       timeout=30)
    return r.returncode, r.stderr.splitlines()


@pytest.mark.parametrize("args, names", OPEN_ERRORS.values(), ids=OPEN_ERRORS.keys())
def test_bus_that_cannot_open_is_an_error_naming_it(args, names):
    rc, stderr = guard_fails(args)
    assert rc != 0
    assert not any("Traceback" in line for line in stderr), stderr
    errors = [line for line in stderr if line.startswith("guard: error: ")]
    assert len(errors) == 1 and all(name in errors[0] for name in names), stderr


@pytest.mark.parametrize("args, names", OPEN_ERRORS.values(), ids=OPEN_ERRORS.keys())
def test_bus_that_cannot_open_is_one_line(args, names):
    rc, stderr = guard_fails(args)
    assert rc != 0 and len(stderr) == 1, stderr


# --- the alarms of a monitor reading CAN, on a MAVLink link that listens (udpin) ------------------------------

def test_a_can_monitor_answers_the_station_its_alarm_link_hears():
    """Reading CAN, guard sends its alarms on link.connect; a udpin link answers whoever it hears, so it
    must be read too: the autopilot (which forwards STATUSTEXT to the ground) sends HEARTBEATs to it and
    gets the attack's alarm."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from guard.config import parse
    from guard.runtime.daemon import Daemon

    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    url = f"can:virtual:alarm-link-{uuid.uuid4().hex[:8]}"
    lines: list[str] = []
    daemon = Daemon(parse({"link": {"connect": f"udpin:127.0.0.1:{port}", "link_timeout_s": 60.0}}),
                    connect=url, out=lines.append)
    thread = threading.Thread(target=daemon.serve, daemon=True)
    thread.start()
    station = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)      # the autopilot's MAVLink side
    station.settimeout(0.05)
    autopilot = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = autopilot.heartbeat_encode(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           0, 0, 0).pack(autopilot)
    texts: list[str] = []
    try:
        deadline = time.monotonic() + 10
        while not daemon.started and time.monotonic() < deadline:
            time.sleep(0.01)
        parser = mavlink.MAVLink(None)
        done = threading.Event()

        def listen():
            while not done.is_set():
                station.sendto(heartbeat, ("127.0.0.1", port))
                with contextlib.suppress(OSError):
                    for msg in parser.parse_buffer(station.recv(4096)) or []:
                        if msg.get_type() == "STATUSTEXT":
                            texts.append(msg.text)
        listener = threading.Thread(target=listen, daemon=True)
        listener.start()
        while daemon.link.peer is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert daemon.link.peer is not None, "the alarm link never heard the autopilot"
        with CanPublisher(url) as publisher:
            run(scenario.load("paper"), 1, can=publisher, fast=True)
        deadline = time.monotonic() + 60
        while not any("ALARM gnss_pos" in t for t in texts) and time.monotonic() < deadline:
            time.sleep(0.05)
        done.set()
        listener.join(timeout=5)
    finally:
        daemon.should_exit = True
        thread.join(timeout=10)
        station.close()
    assert any("GUARD ALARM gnss_pos north" in t for t in texts), (texts, lines)
