"""The alarm where operators look, through a real router: MAVProxy between the autopilot (the
simulator), guard and a separate listening ground station.

MAVProxy forwards what comes in on its `--out` links to the autopilot only: guard's STATUSTEXT reaches
the simulator but never the ground station. With `link.gcs` pointed at a second MAVProxy master,
guard's own messages come into MAVProxy as a vehicle's do and go on to every output, the ground
station's among them. Both topologies are run: the second shows the alarm arriving, the first that it
does not without `link.gcs` (so that the second could fail).

MAVProxy is installed by `make install-test` without its GUI dependencies (Makefile); the test is
skipped, saying so, where it is not installed.
"""

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil   # noqa: E402

BIN = Path(sys.executable).parent
MAVPROXY = shutil.which("mavproxy.py", path=str(BIN)) or shutil.which("mavproxy.py")
GUARD = shutil.which("guard", path=str(BIN)) or shutil.which("guard")
pytestmark = pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (make install-test installs it)")


def free_udp_ports(n: int) -> list[int]:
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def run_topology(tmp_path: Path, with_gcs_link: bool) -> list[tuple[int, int, str]]:
    """(system, component, text) of every STATUSTEXT the ground station received while the paper
    scenario ran at 8x through MAVProxy."""
    master, to_guard, to_gcs, guard_in = free_udp_ports(4)
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{to_gcs}", source_system=255)
    config = tmp_path / "guard.toml"
    config.write_text(f'[link]\ngcs = "udpout:127.0.0.1:{guard_in}"\n' if with_gcs_link else "")
    procs = []
    texts = []
    guard_out = None
    try:
        procs.append(subprocess.Popen(
            [MAVPROXY, f"--master=udpin:127.0.0.1:{master}", f"--master=udpin:127.0.0.1:{guard_in}",
             f"--out=udpout:127.0.0.1:{to_guard}", f"--out=udpout:127.0.0.1:{to_gcs}", "--daemon",
             "--non-interactive", "--default-modules=", f"--state-basedir={tmp_path}"],
            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        guard_out = open(tmp_path / "guard.out", "w")
        procs.append(subprocess.Popen([GUARD, "run", "--connect", f"udpin:127.0.0.1:{to_guard}", "--config",
                                       str(config)], cwd=tmp_path, stdout=guard_out, stderr=subprocess.STDOUT))
        deadline = time.monotonic() + 20
        while "listening on" not in (tmp_path / "guard.out").read_text():
            assert time.monotonic() < deadline and procs[-1].poll() is None, (tmp_path / "guard.out").read_text()
            time.sleep(0.05)
        sim = subprocess.Popen([GUARD, "sim", "--scenario", "paper", "--out", f"udpout:127.0.0.1:{master}",
                                "--speedup", "8"], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(sim)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            msg = gcs.recv_match(type="STATUSTEXT", blocking=True, timeout=0.5)
            if msg is not None:
                texts.append((msg.get_srcSystem(), msg.get_srcComponent(), msg.text))
                if "GUARD ALARM" in msg.text:
                    break
            elif sim.poll() is not None:
                break                       # the scenario is over: no alarm is coming any more
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        gcs.close()
        if guard_out is not None:
            guard_out.close()
    return texts


def test_a_ground_station_behind_mavproxy_gets_the_alarm_through_link_gcs(tmp_path):
    texts = run_topology(tmp_path, with_gcs_link=True)
    alarms = [t for t in texts if "GUARD ALARM" in t[2]]
    assert alarms, texts
    system, component, text = alarms[0]
    assert text.startswith("GUARD ALARM gnss_pos north") and component == 191     # guard's, as an onboard computer


def test_without_link_gcs_mavproxy_keeps_the_alarm_from_the_ground_station(tmp_path):
    texts = run_topology(tmp_path, with_gcs_link=False)
    assert not [t for t in texts if "GUARD" in t[2]], texts
