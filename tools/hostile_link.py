"""A fault campaign on the live link: the paper scenario's frames with hostile ones interleaved.

    python tools/hostile_link.py                      # 10 hostile frames per genuine one (about 10^5)
    python tools/hostile_link.py --ratio 1 --seed 3
    python tools/hostile_link.py --kinds other_sender --senders 100000    # 10^5 spoofed senders

The daemon (`guard run`'s Daemon, in this process, listening on UDP loopback) is fed the paper
scenario (80 s, a 10 m GNSS north step at sample 400) twice: once clean, once with `--ratio` hostile
datagrams sent for every genuine frame, from the autopilot's own address and from another one:

    garbage       1 to 300 random bytes
    truncated     a genuine frame cut short (a partial frame)
    stray         a stray 0xFD byte, alone, or in front of a copy of a genuine frame
    other_system  a valid GPS_RAW_INT from system 2, 50 m away (another vehicle on the link)
    other_sender  a valid GPS_RAW_INT of the autopilot's own system id, 50 m away, from another address
                  (with `--senders N`, from N addresses in turn: 127.0.0.0/8 is all loopback)

Printed: the GNSS sample of each run's first alarm and any alarm before the attack, the daemon
alive, the genuine samples that did not reach the core (a repeat lost with its stray byte is not
one), what it counted as skipped by reason against what was sent, and its resident memory at the
start, the middle and the end of the hostile run (the process's; both runs share it), and the
daemon thread's CPU: per thousand datagrams, and its share of a core over the 3 s after the last
frame (a flood must leave nothing behind that keeps it busy). Exit status 1 if the alarm moved, a
false alarm came or the daemon died.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import socket
import sys
import threading
import time
from collections import Counter
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pymavlink.dialects.v20 import ardupilotmega as mavlink   # noqa: E402

from guard.config import parse                       # noqa: E402
from guard.model.events import Alarm                 # noqa: E402
from guard.runtime.daemon import Daemon              # noqa: E402
from guard.sinks.base import Sink                    # noqa: E402
from guard.sources.mavlink import to_sample          # noqa: E402
from guard_sim import scenario                       # noqa: E402
from guard_sim.run import Simulation                 # noqa: E402

SAMPLE_TYPES = {"GPS_RAW_INT", "RAW_IMU", "ATTITUDE", "HEARTBEAT"}
ATTACK_US = 40_000_000             # the paper scenario's step, at GNSS sample 400 (10 Hz)
KINDS = ("garbage", "truncated", "stray", "other_system", "other_sender")


def key(sample) -> tuple:
    return type(sample).__name__, getattr(sample, "t_us", None), getattr(sample, "lat_deg", None)


class Alarms(Sink):
    """The alarms, and which samples the core was given."""

    def __init__(self):
        self.alarms: list[Alarm] = []
        self.seen: set[tuple] = set()

    def on_sample(self, sample) -> None:
        self.seen.add(key(sample))

    def on_events(self, events) -> None:
        self.alarms += [e for e in events if isinstance(e, Alarm)]


def thread_cpu_s(tid: int) -> float:
    """The CPU time (user + system) of one thread of this process, from /proc."""
    with open(f"/proc/self/task/{tid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Senders:
    """Where other_sender datagrams come from: one socket, or `n` loopback addresses in turn (a
    socket bound to each, opened for one datagram)."""

    def __init__(self, n: int):
        self.n, self.i = n, 0
        self.one = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if n <= 1 else None

    @property
    def addresses(self) -> int:
        """How many addresses sent (not a set of them: this process's memory is measured)."""
        return 1 if self.one is not None else min(self.i, self.n)

    def sendto(self, data: bytes, to) -> None:
        if self.one is not None:
            self.one.sendto(data, to)
            return
        k = self.i % self.n + 2                 # 127.0.0.2 on: 127.0.0.1 is the autopilot's
        self.i += 1
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind((f"127.{k >> 16 & 255}.{k >> 8 & 255}.{k & 255}", 0))
            s.sendto(data, to)

    def close(self) -> None:
        if self.one is not None:
            self.one.close()


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def genuine(seed: int = 1) -> list[tuple[bytes, bool, object]]:
    """(frame, carries a sample, message) of the paper scenario, in order."""
    sim = Simulation(scenario.load("paper"), seed)
    out = []
    for _, msgs in sim.ticks():
        for msg in msgs:
            out.append((sim.encoder.pack(msg), msg.get_type() in SAMPLE_TYPES, msg))
    return out


def hostile(rng: random.Random, frame: bytes, msg, others: dict, kinds=KINDS) -> tuple[str, bytes]:
    kind = rng.choice(kinds)
    if kind == "garbage":
        return kind, rng.randbytes(rng.randint(1, 300))
    if kind == "truncated":
        return kind, frame[:rng.randint(1, max(1, len(frame) - 1))]
    if kind == "stray":
        return kind, b"\xfd" if rng.random() < 0.5 else b"\xfd" + frame
    if msg.get_type() != "GPS_RAW_INT":
        return "garbage", rng.randbytes(rng.randint(1, 40))
    fake = mavlink.MAVLink_gps_raw_int_message(msg.time_usec, msg.fix_type, msg.lat + 4500, msg.lon, msg.alt,
                                               msg.eph, msg.epv, msg.vel, msg.cog, msg.satellites_visible)
    return kind, fake.pack(others[kind])


def run(ratio: float, seed: int, frames, kinds=KINDS, senders: int = 1) -> dict:
    """One run of the daemon over the frames, `ratio` hostile datagrams per genuine frame, the
    other_sender ones from `senders` addresses."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    out: list[str] = []
    d = Daemon(parse({"link": {"link_timeout_s": 30.0}}), connect=f"udpin:127.0.0.1:{port}", out=out.append)
    alarms = Alarms()
    d.pump.sinks.append(alarms)
    thread = threading.Thread(target=d.serve, daemon=True)
    thread.start()
    while not any("listening on" in line for line in out):
        time.sleep(0.01)
    tid = thread.native_id
    cpu0 = thread_cpu_s(tid)
    me, stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), Senders(senders)
    others = {"other_system": mavlink.MAVLink(None, srcSystem=2, srcComponent=1),
              "other_sender": mavlink.MAVLink(None, srcSystem=1, srcComponent=1)}
    rng = random.Random(seed)
    sent, samples, credit, backlog = Counter(), 0, 0.0, 0
    memory = [rss_mb()]
    for i, (frame, is_sample, msg) in enumerate(frames):
        me.sendto(frame, ("127.0.0.1", port))
        samples += is_sample
        credit += ratio
        while credit >= 1.0:
            credit -= 1.0
            kind, data = hostile(rng, frame, msg, others, kinds)
            sent[kind] += 1
            samples += is_sample and len(data) == len(frame) + 1      # a stray byte before a copy: a repeat
            (stranger if kind == "other_sender" else me).sendto(data, ("127.0.0.1", port))
        backlog += 1 + round(ratio)
        last = to_sample(msg)[0]
        if backlog >= 64 and last is not None:   # keep the daemon close behind: the kernel's buffer is not the test
            backlog = 0
            deadline = time.monotonic() + 2.0
            while key(last) not in alarms.seen and time.monotonic() < deadline:
                time.sleep(0.0005)
        if i == len(frames) // 2:
            memory.append(rss_mb())
    deadline = time.monotonic() + 10
    final = next((smp for _, _, m in reversed(frames) if (smp := to_sample(m)[0]) is not None), None)
    while final is not None and key(final) not in alarms.seen and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.5)                     # what came after the last genuine frame
    cpu_busy = thread_cpu_s(tid) - cpu0
    time.sleep(3.0)                     # nothing more is sent: the daemon should idle
    cpu_after = (thread_cpu_s(tid) - cpu0 - cpu_busy) / 3.0
    alive = thread.is_alive()
    skipped = Counter(d.link.skipped) if d.link else Counter()
    d.should_exit = True
    thread.join(timeout=10)
    memory.append(rss_mb())
    me.close()
    stranger.close()
    attack = [a for a in alarms.alarms if a.t_us >= ATTACK_US]
    wanted = {key(sample) for _, _, msg in frames if (sample := to_sample(msg)[0]) is not None}
    return {"first_alarm": attack[0].gnss_index if attack else None,
            "false_alarms": [a.gnss_index for a in alarms.alarms if a.t_us < ATTACK_US],
            "alive": alive, "sent": sent, "skipped": skipped, "samples_taken": d.samples, "samples_sent": samples,
            "genuine_lost": len(wanted - alarms.seen),
            "memory_mb": memory, "cpu_s": cpu_busy, "cpu_after": cpu_after,
            "datagrams": len(frames) + sum(sent.values()), "senders": stranger.addresses,
            "summary": next((line for line in out if line.startswith("guard: stopped")), "")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ratio", type=float, default=10.0, help="hostile datagrams per genuine frame (default 10)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS), help="the kinds of hostile frame sent")
    p.add_argument("--senders", type=int, default=1, help="other_sender datagrams come from this many addresses")
    args = p.parse_args(argv)
    frames = genuine()
    clean = run(0.0, args.seed, frames)
    start = time.monotonic()
    bad = run(args.ratio, args.seed, frames, tuple(args.kinds), args.senders)
    took = time.monotonic() - start
    print(f"genuine frames {len(frames)}, hostile datagrams {sum(bad['sent'].values())} ({dict(bad['sent'])}), "
          f"hostile run {took:.0f} s")
    for name, r in (("clean", clean), ("hostile", bad)):
        print(f"{name:8s} first alarm at GNSS sample {r['first_alarm']}, false alarms {r['false_alarms'] or 'none'}, "
              f"daemon alive {r['alive']}, samples {r['samples_taken']} of {r['samples_sent']} "
              f"({r['genuine_lost']} genuine lost), "
              f"memory {' -> '.join(f'{m:.1f}' for m in r['memory_mb'])} MB, "
              f"daemon CPU {1e6 * r['cpu_s'] / r['datagrams']:.0f} ms per 1000 datagrams "
              f"({r['datagrams']} datagrams), {100 * r['cpu_after']:.1f} % of a core in the 3 s after")
    print(f"hostile: other_sender datagrams came from {bad['senders']} address(es)")
    print(f"hostile: skipped by the link {dict(sorted(bad['skipped'].items()))}")
    print(f"hostile: {re.sub(r'^guard: ', '', bad['summary'])}")
    ok = bad["first_alarm"] == clean["first_alarm"] and not bad["false_alarms"] and bad["alive"] \
        and not bad["genuine_lost"]
    print("same alarm, no false alarm, alive" if ok else "FAILED: the hostile frames changed what guard did")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
