"""CAN decode throughput: guard's CanSource against python-can alone, on the same frames, in one run.

    python tools/bench_can.py [--minutes 3] [--repeat 3] [--scenario clean]

The simulator publishes --minutes of a drive (RAW_IMU at 50 Hz, GNSS at 10 Hz, as DroneCAN RawIMU,
MagneticFieldStrength2 and Fix2) onto a python-can `virtual` bus, where the frames queue up for every
receiver opened beforehand. Then each side drains the same queued frames as fast as it can:
- python-can alone: `bus.recv(0)` until the queue is empty (frames/s);
- guard: `CanSource.poll(0)` once per frame, frames to DroneCAN transfers to samples in SI units
  (frames/s and samples/s), the path of `guard run --connect can:...` without the core.
Each side is timed --repeat times, interleaved (the frames are re-queued, untimed, between rounds),
and the best time of each is kept: the machines are shared and noisy. The ratio is the figure to
compare: it is what the DroneCAN decoding costs on top of reading the bus.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
import uuid
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import can                                       # noqa: E402

from guard.sources.can import CanSource                  # noqa: E402
from guard_sim import scenario                         # noqa: E402
from guard_sim.canbus import CanPublisher              # noqa: E402
from guard_sim.run import run                          # noqa: E402


def channel_url() -> str:
    return f"can:virtual:bench-{uuid.uuid4().hex[:8]}"


def open_receivers(url: str) -> tuple[can.BusABC, CanSource]:
    """Both receivers on one virtual channel, opened before anything is sent (the bus queues per receiver)."""
    bare = can.Bus(interface="virtual", channel=url.split(":", 2)[2])
    return bare, CanSource(url, gnss_node_id=None, imu_node_id=None, timeout_s=3600.0)


def simulate(url: str, name: str, minutes: float) -> float:
    """Publish the drive onto the bus; the wall time it took."""
    sc = scenario.load(name)
    sc = dataclasses.replace(sc, duration_s=minutes * 60,
                             rates=dataclasses.replace(sc.rates, imu_hz=50.0, gnss_hz=10.0, heartbeat_hz=0.0))
    t0 = time.perf_counter()
    with CanPublisher(url) as publisher:
        run(sc, 1, can=publisher, fast=True)
    return time.perf_counter() - t0


def drain_bare(bus: can.BusABC) -> tuple[list, float]:
    frames = []
    t0 = time.perf_counter()
    while (msg := bus.recv(0)) is not None:
        frames.append(msg)
    return frames, time.perf_counter() - t0


def drain_source(source: CanSource, n_frames: int) -> tuple[int, float]:
    """poll() reads exactly one frame when one is queued: n_frames polls read them all."""
    samples = 0
    t0 = time.perf_counter()
    for _ in range(n_frames):
        samples += source.poll(0) is not None
    return samples, time.perf_counter() - t0


def requeue(frames: list) -> tuple[can.BusABC, CanSource]:
    """The same frames onto a fresh channel, for the next round (untimed)."""
    url = channel_url()
    bare, source = open_receivers(url)
    with can.Bus(interface="virtual", channel=url.split(":", 2)[2]) as sender:
        for msg in frames:
            sender.send(can.Message(arbitration_id=msg.arbitration_id, is_extended_id=True, data=msg.data))
    return bare, source


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=3.0, help="simulated minutes of driving")
    p.add_argument("--repeat", type=int, default=3, help="rounds; the best time of each side is kept")
    p.add_argument("--scenario", default="clean")
    args = p.parse_args()
    logging.basicConfig(level=logging.ERROR)        # the source's "reading GNSS from node 10" lines

    url = channel_url()
    bare, source = open_receivers(url)
    sim_s = simulate(url, args.scenario, args.minutes)
    best_bare = best_source = float("inf")
    frames: list = []
    samples = 0
    for round_ in range(args.repeat):
        if round_:
            bare, source = requeue(frames)
        frames, t_bare = drain_bare(bare)
        samples, t_source = drain_source(source, len(frames))
        assert source.poll(0) is None and bare.recv(0) is None, "frames left on the bus"
        best_bare, best_source = min(best_bare, t_bare), min(best_source, t_source)
        stats = {k: v for k, v in source.stats.items() if v}
        messages = dict(source.messages)
        bare.shutdown()
        source.close()

    n = len(frames)
    print(f"scenario {args.scenario}, {args.minutes:g} simulated min (IMU 50 Hz, GNSS 10 Hz), "
          f"best of {args.repeat}")
    print(f"  simulator published {n} frames, {sum(messages.values())} transfers in {sim_s:.1f} s")
    print(f"  transfers decoded: {messages}")
    print(f"  skipped: {stats or 'nothing'}")
    print(f"  python-can alone   : {n / best_bare:10,.0f} frames/s  ({best_bare:.3f} s)")
    print(f"  guard CanSource    : {n / best_source:10,.0f} frames/s  {samples / best_source:9,.0f} samples/s  "
          f"({best_source:.3f} s, {samples} samples)")
    print(f"  ratio              : CanSource takes {best_source / best_bare:.1f}x python-can's time; "
          f"{1e6 * (best_source - best_bare) / n:.1f} us of decoding per frame")
    print(f"  real time          : {n / (args.minutes * 60):,.0f} frames/s on this bus; "
          f"CanSource keeps up {n / best_source / (n / (args.minutes * 60)):,.0f}x over")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
