"""The live path: latency from a GPS_RAW_INT on the socket to the STATUSTEXT it causes, and the
daemon's CPU share and memory while fed 250 Hz IMU + 10 Hz GNSS in real time.

    python tools/bench_live.py [--minutes 10]

This process plays the autopilot: it streams a simulated drive (RAW_IMU 250 Hz, GPS_RAW_INT 10 Hz)
in real time over UDP loopback to a real `guard run` process. Every 10 s a 10 m step on GNSS north
begins for 2 s; guard alarms on the first attacked GPS sample (k = that sample) and, once the step
is gone, clears. Latency = time the STATUSTEXT with k=N arrived here minus the time GPS sample N
left here: it includes both loopback hops, so it bounds guard's own latency from above.
CPU share = the daemon's user + system time while the stream ran / its wall time (from /proc, so
the interpreter's start-up is not counted). Memory: resident set size
sampled every 10 s from /proc (first and last minute compared) and the peak from wait4.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil                    # noqa: E402

from guard_sim import scenario                         # noqa: E402
from guard_sim.run import Simulation                   # noqa: E402
from guard_sim.scenario import Attack                  # noqa: E402


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (from /proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=10.0)
    args = p.parse_args(argv)
    duration = args.minutes * 60
    sc = scenario.load("clean")
    attacks = tuple(Attack("step", "gnss_pos", "north", 10.0, start_s=float(t), duration_s=2.0)
                    for t in range(20, int(duration) - 5, 10))
    sc = dataclasses.replace(sc, duration_s=duration, attacks=attacks,
                             rates=dataclasses.replace(sc.rates, imu_hz=250.0, gnss_hz=10.0))
    port = free_port()
    daemon = subprocess.Popen([sys.executable, "-m", "guard", "run", "--connect", f"udpin:127.0.0.1:{port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert "listening" in daemon.stdout.readline()
    raised: list[str] = []      # the daemon's own alarm lines (its stdout is kept drained)
    threading.Thread(target=lambda: [raised.append(line) for line in daemon.stdout if "GUARD ALARM" in line],
                     daemon=True).start()
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1,
                                      dialect="ardupilotmega")
    sent: dict[int, float] = {}
    latencies: list[float] = []
    stop = threading.Event()

    def receive() -> None:
        while not stop.is_set():
            msg = conn.recv_match(type="STATUSTEXT", blocking=True, timeout=0.2)
            if msg is not None and msg.severity <= 2 and (m := re.search(r"k=(\d+)", msg.text)):
                k = int(m.group(1))
                if k in sent:
                    latencies.append(time.perf_counter() - sent[k])

    rx = threading.Thread(target=receive, daemon=True)
    rx.start()
    sim = Simulation(sc, 1)
    rss: list[tuple[float, int]] = []
    k = -1
    cpu0 = cpu_s(daemon.pid)        # after start-up: what the stream costs, not the interpreter's start
    t_wall0 = time.perf_counter()
    for t_us, messages in sim.ticks():
        while (delay := t_wall0 + t_us / 1e6 - time.perf_counter()) > 0:
            time.sleep(delay)
        for msg in messages:
            frame = sim.encoder.pack(msg)
            if msg.get_type() == "GPS_RAW_INT":     # stamped before it leaves: the answer can beat the next line
                k += 1
                sent[k] = time.perf_counter()
            conn.write(frame)
        if t_us % 10_000_000 == 0:
            rss.append((t_us / 1e6, rss_kb(daemon.pid)))
    wall = time.perf_counter() - t_wall0
    cpu = cpu_s(daemon.pid) - cpu0
    time.sleep(0.5)
    stop.set()
    rx.join()
    daemon.send_signal(signal.SIGTERM)
    _, status, usage = os.wait4(daemon.pid, 0)
    peak_mb = usage.ru_maxrss / 1024 if sys.platform != "darwin" else usage.ru_maxrss / 2**20
    expected = len(attacks)
    lat = sorted(latencies)
    print(f"stream: {args.minutes:g} min real time, RAW_IMU 250 Hz + GPS_RAW_INT 10 Hz, {expected} attacks; "
          f"the daemon raised {len(raised)} alarms, {len(latencies)} arrived here")
    if lat:
        p99 = lat[min(len(lat) - 1, int(round(0.99 * (len(lat) - 1))))]
        print(f"latency GPS_RAW_INT -> STATUSTEXT: p50 {1e3 * statistics.median(lat):.2f} ms, "
              f"p99 {1e3 * p99:.2f} ms, max {1e3 * lat[-1]:.2f} ms over {len(lat)} alarms (target p99 < 5 ms)")
    else:
        print("latency: no alarm received")
    print(f"daemon CPU: {cpu:.1f} s over {wall:.0f} s wall = {100 * cpu / wall:.1f} % of one core (target < 10 %)")
    first = [kb for t, kb in rss if t <= 60] or [rss[0][1]]
    last = [kb for t, kb in rss if t >= rss[-1][0] - 60]
    print(f"daemon memory: RSS first minute {max(first) / 1024:.1f} MB, last minute {max(last) / 1024:.1f} MB, "
          f"peak {peak_mb:.1f} MB")
    return 0 if lat and len(lat) >= expected * 0.9 else 1


if __name__ == "__main__":
    raise SystemExit(main())
