"""`guard demo`: the simulator and the daemon as two processes on UDP loopback.

The daemon (`guard run`) listens on a free loopback port; the simulator, in this process, plays
the autopilot: it streams the scenario at a speed-up and prints every STATUSTEXT it receives, as a
ground station would. At the end, one verdict line compares the first alarm with the truth.
"""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import os
import threading
import time

from guard.errors import GuardError


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def verdict(truth: dict, received: list[tuple[int, str]]) -> str:
    """One line: was the attack caught, how late, and were there false alarms."""
    alarms = [int(m.group(1)) for sev, text in received if sev <= 2 and (m := re.search(r"k=(\d+)", text))]
    attacks = truth["attacks"]
    if not attacks:
        return "verdict: no attack, " + (f"but {len(alarms)} FALSE ALARM(S)" if alarms else "no alarm: correct")
    k0 = min(a["start_gnss_index"] for a in attacks)
    # an alarm's k is the last fix before it: an attack on the IMU or the magnetometer that starts between
    # two fixes may be caught before the next one, at k0 - 1 (an alarm names no time to tell more)
    first = min(a["start_gnss_index"] - (not a["sensor"].startswith("gnss")) for a in attacks)
    what = ", ".join(f"{a['kind']} on {a['sensor']} {a['channel']}" for a in attacks)
    false = [k for k in alarms if k < first]
    caught = [k for k in alarms if k >= first]
    if not caught:
        return f"verdict: {what} at GNSS sample {k0} MISSED" + (f", {len(false)} false alarm(s)" if false else "")
    return (f"verdict: {what} at GNSS sample {k0} caught at sample {caught[0]} "
            f"({max(0, caught[0] - k0)} samples late), "
            + (f"{len(false)} FALSE ALARM(S)" if false else "no false alarm"))


def demo(scenario_name: str, seed: int, speedup: float) -> int:
    from guard_sim import scenario
    from guard_sim.run import run
    try:
        sc = scenario.load(scenario_name)
    except scenario.ScenarioError as e:
        raise GuardError(str(e)) from None
    port = _free_udp_port()
    monitor = subprocess.Popen([sys.executable, "-m", "guard", "run", "--connect", f"udpin:127.0.0.1:{port}"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    ready = threading.Event()

    def relay() -> None:
        for line in monitor.stdout:
            if "listening on" in line:
                ready.set()
            print(f"[monitor] {line.rstrip()}", flush=True)

    threading.Thread(target=relay, daemon=True).start()
    if not ready.wait(30):
        monitor.kill()
        raise GuardError("the monitor did not start within 30 s")
    print(f"[sim] scenario {sc.name} ({sc.description}), seed {seed}, {sc.duration_s:.0f} s at {speedup:g}x "
          f"-> udpout:127.0.0.1:{port}", flush=True)
    received: list[tuple[int, str]] = []

    def show(msg) -> None:
        received.append((msg.severity, msg.text))
        label = {2: "CRITICAL", 4: "WARNING", 5: "NOTICE", 6: "INFO"}.get(msg.severity, str(msg.severity))
        print(f"[ground station] {label}: {msg.text}", flush=True)

    try:
        truth = run(sc, seed, out=f"udpout:127.0.0.1:{port}", speedup=speedup, on_statustext=show)
    finally:
        monitor.terminate()
        try:
            monitor.wait(10)
        except subprocess.TimeoutExpired:
            monitor.kill()
        time.sleep(0.1)
    print(verdict(truth, received), flush=True)
    return 0
