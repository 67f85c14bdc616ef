"""The systemd unit (checked by `systemd-analyze verify`) and the notify protocol (against a real socket)."""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from guard.runtime import sdnotify
from guard.runtime.sdnotify import Notifier

UNIT = Path(__file__).resolve().parents[2] / "configs" / "systemd" / "guard.service"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd_analyze = pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze is not on PATH")


# --- The unit file ----------------------------------------------------------------------------------------

def read_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """Parse a unit file into {section: {key: [values in order]}}; keys may repeat (SystemCallFilter=)."""
    sections: dict[str, dict[str, list[str]]] = {}
    section = None
    for line in text.splitlines():
        line = line.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            section = sections.setdefault(line[1:-1], {})
        else:
            key, _, value = line.partition("=")
            section.setdefault(key.strip(), []).append(value.strip())
    return sections


def copy_for_verify(tmp_path: Path, *replacements: tuple[str, str]) -> Path:
    """Copy the unit to tmp_path with ExecStart's program (absent here) replaced by this Python."""
    lines = []
    for line in UNIT.read_text().splitlines():
        if line.startswith("ExecStart="):
            _, *args = line.removeprefix("ExecStart=").split()
            line = " ".join([f'ExecStart="{sys.executable.replace("%", "%%")}"', *args])
        for old, new in replacements:
            line = new if line == old else line
        lines.append(line)
    copy = tmp_path / UNIT.name
    copy.write_text("\n".join(lines) + "\n")
    return copy


def verify(path: Path) -> tuple[int, list[str]]:
    """Run `systemd-analyze verify`; return its exit status and the output lines that name the unit.

    The exit status alone is not enough: systemd (252 at least) only warns and exits 0 on a value it cannot
    parse ("Failed to parse service type, ignoring: bogus"), so any line about the unit counts as a problem.
    """
    done = subprocess.run([SYSTEMD_ANALYZE, "verify", str(path)], capture_output=True, text=True, timeout=60)
    lines = (done.stdout + done.stderr).splitlines()
    return done.returncode, [line for line in lines if path.name in line]


def test_unit_has_the_key_settings():
    unit = read_unit(UNIT.read_text())
    service = {key: values[-1] for key, values in unit["Service"].items()}
    assert service["Type"] == "notify"
    assert service["NotifyAccess"] == "main"
    assert service["ExecStart"] == "/opt/guard/.venv/bin/guard run --config /etc/guard/guard.toml --mcap /var/log/guard"
    assert int(service["WatchdogSec"]) > 0
    assert service["Restart"] == "on-failure"
    assert service["RestartPreventExitStatus"] == "78"     # guard's exit status on a config error
    assert service["NoNewPrivileges"] == "yes"
    assert service["ProtectSystem"] == "strict"
    assert "/var/log/guard" in service["ReadWritePaths"].split()
    assert "dialout" in service["SupplementaryGroups"].split()
    assert "AF_CAN" in service["RestrictAddressFamilies"].split()
    assert int(service["TimeoutStopSec"]) > 0
    assert "network-online.target" in unit["Unit"]["After"][-1].split()
    assert unit["Install"]["WantedBy"] == ["multi-user.target"]
    # The serial ports stay reachable (see the unit's comments): no PrivateDevices=, and the device
    # allow-list names every kind of port a flight controller appears as.
    assert "PrivateDevices" not in service
    assert service["DevicePolicy"] == "closed"
    assert {"char-ttyACM rw", "char-ttyUSB rw", "char-ttyAMA rw", "char-ttyS rw"} <= set(unit["Service"]["DeviceAllow"])


@needs_systemd_analyze
def test_the_units_exposure_is_low(tmp_path):
    """`systemd-analyze security` on the unit as installed: at most 2.0 of 10 ("OK"; README)."""
    out = subprocess.run([SYSTEMD_ANALYZE, "security", "--offline=true", str(copy_for_verify(tmp_path))],
                         capture_output=True, text=True, timeout=60)
    if "--offline" in out.stderr and out.returncode != 0:
        pytest.skip(f"this systemd-analyze cannot check offline: {out.stderr.strip()[:80]}")
    level = [line for line in out.stdout.splitlines() if "Overall exposure level" in line]
    assert level, out.stdout[-500:] + out.stderr[-500:]
    assert float(level[0].split(":")[1].split()[0]) <= 2.0, level[0]


@needs_systemd_analyze
def test_systemd_analyze_verify_accepts_the_unit(tmp_path):
    returncode, problems = verify(copy_for_verify(tmp_path))
    assert (returncode, problems) == (0, [])


@needs_systemd_analyze
@pytest.mark.parametrize("old, new", [("Type=notify", "Type=bogus"),
                                      ("ProtectSystem=strict", "ProtectSystem=maybe")])
def test_systemd_analyze_verify_rejects_a_broken_unit(tmp_path, old, new):
    returncode, problems = verify(copy_for_verify(tmp_path, (old, new)))
    assert returncode != 0 or problems


@needs_systemd_analyze
def test_systemd_analyze_verify_rejects_a_missing_program(tmp_path):
    # Why copy_for_verify rewrites ExecStart: the installed path does not exist on the test machine.
    copy = tmp_path / UNIT.name
    copy.write_text(UNIT.read_text().replace("/opt/guard/.venv/bin/guard", str(tmp_path / "absent")))
    assert verify(copy)[0] != 0


# --- The notify protocol ----------------------------------------------------------------------------------

class FakeClock:
    """A monotonic clock the test moves by hand, in seconds."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def received(sock: socket.socket) -> list[str]:
    """Every datagram waiting on `sock` (sendto on a unix socket has queued it before returning)."""
    messages = []
    while True:
        try:
            messages.append(sock.recv(4096, socket.MSG_DONTWAIT).decode())
        except BlockingIOError:
            return messages


@pytest.fixture
def notify_socket(tmp_path, monkeypatch):
    """A unix datagram socket bound in tmp_path and named by NOTIFY_SOCKET, without a watchdog."""
    path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        monkeypatch.delenv("WATCHDOG_USEC", raising=False)
        monkeypatch.delenv("WATCHDOG_PID", raising=False)
        yield sock


def test_ready_status_stopping(notify_socket):
    notifier = Notifier()
    assert notifier.enabled and notifier.watchdog_interval_s is None
    notifier.ready()
    notifier.ready(status="reading udpin:0.0.0.0:14550")
    notifier.status("ekf converged")
    notifier.stopping()
    assert received(notify_socket) == [
        "READY=1", "READY=1\nSTATUS=reading udpin:0.0.0.0:14550", "STATUS=ekf converged", "STOPPING=1"]


def test_status_stays_on_one_line(notify_socket):
    Notifier().status("gnss alarm\nSTOPPING=1")
    assert received(notify_socket) == ["STATUS=gnss alarm STOPPING=1"]


def test_watchdog_is_rate_limited_to_half_the_interval(notify_socket, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "10000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    clock = FakeClock()
    notifier = Notifier(clock=clock)
    assert notifier.watchdog_interval_s == 10.0
    notifier.watchdog()
    notifier.watchdog()
    assert received(notify_socket) == ["WATCHDOG=1"]
    clock.now_s += 4.9
    notifier.watchdog()
    assert received(notify_socket) == []
    clock.now_s += 0.1
    notifier.watchdog()
    notifier.watchdog()
    assert received(notify_socket) == ["WATCHDOG=1"]


def test_watchdog_with_the_real_clock(notify_socket, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "200000")   # half interval 0.1 s
    notifier = Notifier()
    notifier.watchdog()
    notifier.watchdog()
    assert received(notify_socket) == ["WATCHDOG=1"]
    time.sleep(0.12)
    notifier.watchdog()
    assert received(notify_socket) == ["WATCHDOG=1"]


@pytest.mark.parametrize("usec, pid", [("10000000", "1"), ("0", ""), ("ten", ""), ("", "")])
def test_no_watchdog_unless_meant_for_us(notify_socket, monkeypatch, usec, pid):
    monkeypatch.setenv("WATCHDOG_USEC", usec)
    monkeypatch.setenv("WATCHDOG_PID", pid)
    notifier = Notifier()
    notifier.watchdog()
    assert notifier.watchdog_interval_s is None
    assert received(notify_socket) == []


def test_abstract_socket(monkeypatch):
    name = f"guard-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        Notifier().ready(status="up")
        assert received(sock) == ["READY=1\nSTATUS=up"]


def test_no_op_without_notify_socket(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.setenv("WATCHDOG_USEC", "200000")

    def no_socket(*args, **kwargs):
        raise AssertionError("a socket was opened without NOTIFY_SOCKET")

    monkeypatch.setattr(sdnotify.socket, "socket", no_socket)
    notifier = Notifier()
    assert not notifier.enabled and notifier.watchdog_interval_s is None
    notifier.ready(status="up")
    notifier.status("running")
    notifier.watchdog()
    notifier.stopping()


def test_vanished_socket_warns_once_and_does_not_raise(notify_socket, caplog):
    notifier = Notifier()
    notify_socket.close()
    Path(os.environ["NOTIFY_SOCKET"]).unlink()
    with caplog.at_level(logging.DEBUG, logger="guard.runtime.sdnotify"):
        notifier.ready()
        notifier.status("still running")
        notifier.stopping()
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "notify" in warnings[0].getMessage()
