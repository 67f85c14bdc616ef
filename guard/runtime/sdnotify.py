"""The systemd notify protocol (sd_notify(3)): tell the service manager we are ready, alive, stopping.

systemd passes the address of a unix datagram socket in NOTIFY_SOCKET (a filesystem path, or an abstract
name written with a leading '@'); each message is one datagram of newline-separated `KEY=value` lines.
When the unit sets WatchdogSec=, systemd also passes WATCHDOG_USEC (the interval, in integer
microseconds) and WATCHDOG_PID (the process meant to ping); the service must send WATCHDOG=1 more often
than that or it is killed and, with Restart=on-failure, restarted.

Outside systemd (NOTIFY_SOCKET unset) every method is a cheap no-op, so the daemon calls them
unconditionally. Sending never raises: a lost notification must not stop estimation.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

logger = logging.getLogger(__name__)


class Notifier:
    """Sends READY=1, STATUS=..., WATCHDOG=1 and STOPPING=1 to the socket named by the environment.

    `environ` defaults to os.environ, read once here; `clock` returns seconds (time.monotonic) and is
    only used to rate-limit the watchdog, so tests may pass a fake one.
    """

    def __init__(self, environ: Mapping[str, str] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        env = os.environ if environ is None else environ
        self._address = _socket_address(env.get("NOTIFY_SOCKET", ""))
        self._watchdog_usec = _watchdog_usec(env) if self._address is not None else None
        self._clock = clock
        self._last_ping_s: float | None = None   # clock() at the last WATCHDOG=1, None before the first
        self._warned = False                     # a send failure is logged at warning only once

    @property
    def enabled(self) -> bool:
        """True when running under systemd with a notify socket."""
        return self._address is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """The watchdog interval in seconds, or None when there is no watchdog (or no notify socket)."""
        return None if self._watchdog_usec is None else self._watchdog_usec / 1e6

    def ready(self, status: str | None = None) -> None:
        """Start-up is finished (Type=notify units are 'active' only from now on)."""
        self._send("READY=1" if status is None else f"READY=1\nSTATUS={_one_line(status)}")

    def status(self, text: str) -> None:
        """A one-line state shown by `systemctl status guard`."""
        self._send(f"STATUS={_one_line(text)}")

    def watchdog(self) -> None:
        """Ping the watchdog, at most once per half interval; cheap enough to call every loop iteration."""
        if self._watchdog_usec is None:
            return
        now_s = self._clock()
        if self._last_ping_s is not None and now_s - self._last_ping_s < self._watchdog_usec / 2e6:
            return
        self._last_ping_s = now_s
        self._send("WATCHDOG=1")

    def stopping(self) -> None:
        """Shutdown has begun."""
        self._send("STOPPING=1")

    def _send(self, message: str) -> None:
        """Send one datagram; on failure log a warning the first time and debug after that."""
        if self._address is None:
            return
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.sendto(message.encode(), self._address)
        except OSError as exc:
            log = logger.debug if self._warned else logger.warning
            self._warned = True
            log("systemd notify to %r failed: %s", self._address, exc)


def _socket_address(value: str) -> str | None:
    """NOTIFY_SOCKET as an AF_UNIX address: '@name' is the abstract '\\0name'; unset or unusable -> None."""
    if value.startswith("@") and len(value) > 1:
        return "\0" + value[1:]
    if value.startswith("/"):
        return value
    if value:
        logger.warning("ignoring NOTIFY_SOCKET=%r: neither an absolute path nor '@' abstract name", value)
    return None


def _watchdog_usec(env: Mapping[str, str]) -> int | None:
    """WATCHDOG_USEC when it is a positive integer meant for this process (WATCHDOG_PID), else None."""
    usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
    if not usec:
        return None
    if pid and pid != str(os.getpid()):
        return None   # the watchdog belongs to another process (e.g. we were forked or exec'ed by it)
    if not usec.isdigit() or int(usec) == 0:
        logger.warning("ignoring WATCHDOG_USEC=%r: not a positive integer", usec)
        return None
    return int(usec)


def _one_line(text: str) -> str:
    """Keep a status on one line: a newline would start a new assignment (e.g. an injected STOPPING=1)."""
    return " ".join(text.splitlines())
