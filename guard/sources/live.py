"""Live sources, chosen by the connection URL's scheme: `can:` is DroneCAN through python-can (imported
only then), anything else a pymavlink connection (`udpin:`, `udpout:`, `tcp:`, a serial device).

A URL's form is checked before anything is opened (`check_url`): pymavlink reads any string it does not
recognise as a serial port or a log file, runs a file whose path holds `/bin/`, and exits the process on
a UDP address without a port. A serial device is then looked for (`check_serial_device`).
"""

from __future__ import annotations

import grp
import importlib.util
import os
import stat

from guard.errors import ConfigError, SourceError
from guard.sources.link import MavlinkLink

FORMS = ("udpin:HOST:PORT (listen), udpout:HOST:PORT (send), udpbcast:ADDRESS:PORT, mcast:[GROUP:PORT], "
         "tcp:HOST:PORT, tcpin:HOST:PORT, a serial device DEVICE[,BAUD] (e.g. /dev/ttyACM0,57600; "
         "default 115200 baud), can:INTERFACE:CHANNEL (e.g. can:socketcan:can0)")
LISTEN = {"udpin", "tcpin"}                         # port 0: any free port
SEND = {"udpout", "udpbcast", "tcp", "mcast"}


def open_link(url: str, cfg):
    """The live source for `url` with guard's configuration `cfg` (its `link` and `can` sections)."""
    kind = check_url(url)
    if kind == "can":
        from guard.sources.can import CanSource      # python-can and dronecan only when CAN is configured
        c = cfg.can
        return CanSource(url, gnss_node_id=c.gnss_node_id or None, imu_node_id=c.imu_node_id or None,
                         timeout_s=cfg.link.link_timeout_s, time_source=c.time_source)
    if kind == "serial":
        check_serial_device(url.partition(",")[0])
    return MavlinkLink(url, cfg.link, cfg.monitor.min_imu_hz)


def check_url(url: str) -> str:
    """The kind of a connection URL ("udp", "tcp", "serial" or "can"); ConfigError naming the accepted
    forms unless it has one of them."""
    def bad(why: str) -> ConfigError:
        return ConfigError(f"bad connection URL {url!r}: {why}; expected one of: {FORMS}")

    if url.startswith(("/", "./", "../")) or (url[:3].upper() == "COM" and url[3:].partition(",")[0].isdigit()):
        device, comma, baud = url.partition(",")
        if ":" in device:       # pymavlink would take it for a UDP address
            raise bad("a serial device path with ':' (e.g. /dev/serial/by-path/...) is read as a UDP "
                      "address by pymavlink; give its /dev/serial/by-id/... name or the /dev/tty... it links to")
        if comma and not (baud.isdigit() and int(baud) > 0):
            raise bad(f"the baud rate after ',' must be a positive whole number, not {baud!r}")
        return "serial"
    scheme, colon, rest = url.partition(":")
    if not colon:
        raise bad("no scheme (a serial device is given by its path, e.g. /dev/ttyUSB0)")
    if scheme == "can":
        interface, _, channel = rest.partition(":")
        if not interface or not channel:
            raise bad("a CAN bus needs an interface and a channel")
        return "can"
    if scheme == "udp":
        raise bad("'udp:' is ambiguous (pymavlink listens, MAVProxy's --out sends): write udpin: to listen "
                  "or udpout: to send")
    if scheme not in LISTEN | SEND:
        raise bad(f"unknown scheme {scheme + ':'!r}")
    if scheme == "mcast" and not rest:
        return "udp"
    host, colon, port = rest.partition(":")
    if not host or not colon or ":" in port or any(c.isspace() for c in host):
        raise bad(f"{scheme}: needs HOST:PORT (an IPv4 address or a name, then the port)")
    lowest = 0 if scheme in LISTEN else 1
    if not (port.isdigit() and lowest <= int(port) <= 65535):
        raise bad(f"the port must be a number {lowest}..65535, not {port!r}")
    return "tcp" if scheme.startswith("tcp") else "udp"


def check_serial_device(device: str) -> None:
    """SourceError unless `device` is a character device this process may open (a missing device may
    yet be plugged in); ConfigError if it is a file or folder (a log goes to `guard replay`)."""
    if importlib.util.find_spec("serial") is None:
        raise SourceError(f"serial device {device}: serial links need pyserial (pip install pyserial)")
    try:
        st = os.stat(device)
    except FileNotFoundError:
        raise SourceError(f"serial device {device} does not exist (is the flight controller plugged in "
                          "and powered? ls /dev/serial/by-id/ lists the serial devices)") from None
    except OSError as e:
        raise SourceError(f"serial device {device}: {e.strerror}") from None
    if not stat.S_ISCHR(st.st_mode):
        what = "a folder" if stat.S_ISDIR(st.st_mode) else "a file"
        raise ConfigError(f"{device} is {what}, not a serial device (a log is read with guard replay FILE)")
    if not os.access(device, os.R_OK | os.W_OK):
        try:
            group = f"; its group is {grp.getgrgid(st.st_gid).gr_name}: add the user to it"
        except KeyError:
            group = ""
        raise SourceError(f"serial device {device}: permission denied{group}")
