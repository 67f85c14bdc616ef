"""`guard run` on a serial link: the simulator on one serial device, the daemon on another, and the two
devices joined like a null-modem cable.

Two pseudo-terminals stand in for the two ends (no hardware, no socat): the test copies what is written on
one's device to the other's, both ways, as the cable would. `guard sim --out DEVICE,57600` plays the
flight controller and `guard run --connect DEVICE,57600` the companion computer; the alarm must come back
over the cable as a STATUSTEXT that the simulator prints as a ground station would.
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import signal
import threading
import tty

import pytest

from system.test_daemon import procs             # noqa: F401 (the fixture)

pytestmark = pytest.mark.slow


@contextlib.contextmanager
def null_modem():
    """Two serial devices (pseudo-terminals) joined both ways; yields their paths and the bytes carried
    each way ([a to b, b to a])."""
    pairs = [os.openpty() for _ in range(2)]
    for _, device in pairs:
        tty.setraw(device)          # binary: no echo, no line editing (pyserial sets the same on open)
    masters = [master for master, _ in pairs]
    for master in masters:
        os.set_blocking(master, False)
    carried, stop = [0, 0], threading.Event()

    def cable() -> None:
        while not stop.is_set():
            ready, _, _ = select.select(masters, [], [], 0.05)
            for i, master in enumerate(masters):
                if master not in ready:
                    continue
                try:
                    data = os.read(master, 4096)
                    carried[i] += os.write(masters[1 - i], data)    # the rest is lost, as on a full line
                except (BlockingIOError, InterruptedError):
                    pass

    thread = threading.Thread(target=cable, daemon=True)
    thread.start()
    try:
        yield [os.ttyname(device) for _, device in pairs], carried
    finally:
        stop.set()
        thread.join(5)
        for fd in (fd for pair in pairs for fd in pair):
            os.close(fd)


def test_alarm_over_a_serial_link(procs):                        # noqa: F811 (the fixture imported above)
    with null_modem() as ((autopilot, companion), carried):
        daemon = procs("run", "--connect", f"{companion},57600")
        daemon.wait_line("listening on")
        sim = procs("sim", "--scenario", "paper", "--seed", "7", "--out", f"{autopilot},57600", "--speedup", "10")
        assert sim.wait(60) == 0, sim.stderr
        critical = [line for line in sim.stdout if line.startswith("[ground station] CRITICAL:")]
        assert critical, (sim.stdout, daemon.stdout, daemon.stderr, carried)
        assert "GUARD ALARM gnss_pos north" in critical[0], critical[0]
        first = int(re.search(r"k=(\d+)", critical[0]).group(1))
        assert 400 <= first <= 405, f"first alarm at GNSS sample {first}, the attack starts at 400"
        assert carried[0] > 20_000 and carried[1] > 0, carried
        daemon.p.send_signal(signal.SIGTERM)
        assert daemon.wait(15) == 0, daemon.stderr
