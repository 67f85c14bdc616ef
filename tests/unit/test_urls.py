"""Connection URLs (guard.sources.live): their form is checked before anything is opened, and a serial
device is looked for, with errors that name the accepted forms or the device."""

from __future__ import annotations

import os

import pytest

from guard.cli import EX_CONFIG, main
from guard.errors import ConfigError, SourceError
from guard.sources.live import check_serial_device, check_url


@pytest.mark.parametrize("url, kind", [
    ("udpin:0.0.0.0:14550", "udp"),
    ("udpin:127.0.0.1:0", "udp"),                   # any free port
    ("udpout:127.0.0.1:14550", "udp"),
    ("udpout:gcs.local:14550", "udp"),
    ("udpbcast:192.168.1.255:14550", "udp"),
    ("mcast:", "udp"),
    ("tcp:127.0.0.1:5760", "tcp"),
    ("tcpin:0.0.0.0:5760", "tcp"),
    ("/dev/ttyACM0", "serial"),
    ("/dev/ttyAMA0,921600", "serial"),
    ("/dev/serial/by-id/usb-ArduPilot_fmuv3_1E0030001851353036383238-if00,57600", "serial"),
    ("./ttyV0,57600", "serial"),
    ("COM3,57600", "serial"),
    ("can:socketcan:can0", "can"),
    ("can:udp_multicast:239.74.163.2", "can"),
])
def test_accepted_forms(url, kind):
    assert check_url(url) == kind


@pytest.mark.parametrize("url, why", [
    ("", "no scheme"),
    ("ttyUSB0", "no scheme"),
    ("udp:0.0.0.0:14550", "ambiguous"),
    ("udpin:14550", "needs HOST:PORT"),
    ("udpin:0.0.0.0", "needs HOST:PORT"),
    ("udpout::14550", "needs HOST:PORT"),
    ("udpin:[::1]:14550", "needs HOST:PORT"),
    ("udpout:127.0.0.1:0", "1..65535"),
    ("tcp:127.0.0.1:65536", "1..65535"),
    ("tcp:127.0.0.1:port", "1..65535"),
    ("http://127.0.0.1:14550", "unknown scheme"),
    ("ws:127.0.0.1:14550", "unknown scheme"),
    ("/dev/ttyACM0,fast", "baud"),
    ("/dev/ttyACM0,57600,8N1", "baud"),
    ("/dev/ttyACM0,0", "baud"),
    ("/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0-port0", "by-id"),
    ("can:socketcan", "interface and a channel"),
    ("can::can0", "interface and a channel"),
])
def test_rejected_forms_name_the_accepted_ones(url, why):
    with pytest.raises(ConfigError) as e:
        check_url(url)
    text = str(e.value)
    assert why in text and repr(url) in text
    for form in ("udpin:HOST:PORT", "udpout:HOST:PORT", "tcp:HOST:PORT", "DEVICE[,BAUD]", "can:INTERFACE:CHANNEL"):
        assert form in text


def test_a_missing_serial_device_is_named(tmp_path):
    device = str(tmp_path / "ttyACM9")
    with pytest.raises(SourceError, match=f"serial device {device} does not exist"):
        check_serial_device(device)


def test_a_file_is_not_a_serial_device(tmp_path):
    log = tmp_path / "flight.tlog"
    log.write_bytes(b"")
    with pytest.raises(ConfigError, match="not a serial device.*guard replay"):
        check_serial_device(str(log))
    with pytest.raises(ConfigError, match="a folder"):
        check_serial_device(str(tmp_path))


def test_a_pty_is_a_serial_device():
    master, slave = os.openpty()
    try:
        check_serial_device(os.ttyname(slave))
    finally:
        os.close(master)
        os.close(slave)


def test_guard_run_says_which_device_is_missing(tmp_path, capsys):
    """One line naming the device, exit 1 (systemd restarts: it may yet be plugged in), no 'No module'."""
    device = tmp_path / "ttyUSB7"
    assert main(["run", "--connect", f"{device},57600"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"serial device {device} does not exist" in err, err
    assert "No module" not in err


def test_guard_run_rejects_a_bad_url_as_a_config_error(capsys):
    assert main(["run", "--connect", "udp:0.0.0.0:14550"]) == EX_CONFIG
    err = capsys.readouterr().err
    assert "udpin:HOST:PORT" in err and "No module" not in err
