"""Fault campaigns against the daemon: a silent link, an autopilot reboot, SIGKILL, a full disk, a long run.

    python tools/faults.py silence              # the link silent 2, 8 and 20 s, before the attack and during it
    python tools/faults.py reboot               # the autopilot reboots before the attack, after its alarm; a lone
                                                # wild stamp
    python tools/faults.py kill --kills 10      # `guard run --mcap` killed at random moments, then mcap-recover
    python tools/faults.py disk                 # the MCAP log directory on a 256 kB tmpfs that fills (needs root)
    python tools/faults.py memory --minutes 60 --speedup 4   # resident memory over an hour of driving

Each campaign feeds the paper scenario (80 s, GNSS at 10 Hz, a 10 m GNSS north step from 40 s: GNSS
sample 400) over UDP loopback to guard's daemon (`guard.runtime.daemon.Daemon` in this process, or
`guard run` as a process for `kill`), prints what happened per case, and exits 1 if guard did what
it must not: a missed or false alarm, an alarm cleared by the fault, a dead daemon, a loss past one
chunk, memory that grows. Delays are in GNSS samples after the attack's first sample.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mcap.reader import make_reader                        # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink   # noqa: E402

from guard.config import parse                             # noqa: E402
from guard.model.events import Alarm, Cleared              # noqa: E402
from guard.runtime.daemon import Daemon                    # noqa: E402
from guard.sinks.base import Sink                          # noqa: E402
from guard_sim import scenario                             # noqa: E402
from guard_sim.run import Simulation                       # noqa: E402

ATTACK_US = 40_000_000              # the paper scenario's step: GNSS sample 400 at 10 Hz
GNSS_PERIOD_US = 100_000
TIMED = {"GPS_RAW_INT": "time_usec", "RAW_IMU": "time_usec", "ATTITUDE": "time_boot_ms",
         "SCALED_PRESSURE": "time_boot_ms", "SYSTEM_TIME": "time_boot_ms"}


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def messages(name: str = "paper", seed: int = 1, minutes: float | None = None):
    """(t_us, message) of a scenario, in order, lazily; `minutes` overrides its length."""
    sc = scenario.load(name)
    if minutes is not None:
        sc = dataclasses.replace(sc, duration_s=60.0 * minutes)
    for t_us, msgs in Simulation(sc, seed).ticks():
        for msg in msgs:
            yield t_us, msg


def retimed(msg, shift_us: int):
    """A copy of `msg` with its time stamp moved by shift_us (what a reboot does to the boot clock)."""
    field = TIMED.get(msg.get_type())
    if field is None:
        return msg
    copy = type(msg)(*[getattr(msg, f) for f in msg.fieldnames])
    unit = 1000 if field == "time_boot_ms" else 1
    setattr(copy, field, max(0, getattr(msg, field) + shift_us // unit))
    return copy


class Events(Sink):
    """What the core said: alarms, clears, and the time of the last sample it was given."""

    def __init__(self):
        self.alarms: list[Alarm] = []
        self.cleared: list[Cleared] = []
        self.taken = 0

    def on_sample(self, sample) -> None:
        self.taken += 1

    def on_events(self, events) -> None:
        self.alarms += [e for e in events if isinstance(e, Alarm)]
        self.cleared += [e for e in events if isinstance(e, Cleared)]


class Lines(logging.Handler):
    """The operator's lines (guard logs them), kept."""

    def __init__(self, lines: list[str]):
        super().__init__(logging.INFO)
        self.lines = lines

    def emit(self, record) -> None:
        self.lines.append(record.getMessage())


class Rig:
    """The daemon in a thread of this process, listening on UDP loopback, and an autopilot that sends to it."""

    def __init__(self, settings: dict | None = None, mcap: str | None = None):
        self.port = free_udp_port()
        cfg = {"link": {"link_timeout_s": 5.0}} | (settings or {})
        self.lines: list[str] = []
        self.handler = Lines(self.lines)
        logger = logging.getLogger("guard")
        self.level = logger.level
        logger.addHandler(self.handler)
        logger.setLevel(logging.INFO)
        self.daemon = Daemon(parse(cfg), connect=f"udpin:127.0.0.1:{self.port}", mcap=mcap or "",
                             out=self.lines.append)
        self.events = Events()
        self.daemon.pump.sinks.append(self.events)
        self.thread = threading.Thread(target=self.daemon.serve, daemon=True)
        self.thread.start()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.sent = 0
        deadline = time.monotonic() + 10
        while not self.daemon.started and time.monotonic() < deadline:
            time.sleep(0.01)

    def send(self, msg) -> None:
        self.sock.sendto(msg.pack(self.mav), ("127.0.0.1", self.port))
        self.sent += 1
        if self.sent % 32 == 0:             # keep the daemon close behind (the kernel's buffer is not the test)
            deadline = time.monotonic() + 2.0
            while self.events.taken < self.sent * 0.9 - 64 and time.monotonic() < deadline:
                time.sleep(0.0005)

    def settle(self, seconds: float = 1.0) -> None:
        time.sleep(seconds)

    def stop(self) -> dict:
        alive = self.thread.is_alive()
        self.daemon.should_exit = True
        self.thread.join(timeout=10)
        self.sock.close()
        logging.getLogger("guard").removeHandler(self.handler)
        logging.getLogger("guard").setLevel(self.level)
        return {"alive": alive, "lines": self.lines, "alarms": self.events.alarms, "cleared": self.events.cleared,
                "excluded": set(self.daemon.monitor.alarmed)}


def first_attack_alarm(alarms, after_us: int = ATTACK_US):
    return next((a for a in alarms if a.t_us >= after_us and a.sensor == "gnss_pos"), None)


def delay_samples(alarm, attack_us: int = ATTACK_US) -> int | None:
    return None if alarm is None else round((alarm.t_us - attack_us) / GNSS_PERIOD_US)


# -- silence ----------------------------------------------------------------------------------------

def silence_case(gap_s: float, at_s: float, seed: int = 1) -> dict:
    """The link silent for gap_s of wall clock from vehicle time at_s; the gap's frames are never sent."""
    rig = Rig()
    start_us, end_us, silent = int(at_s * 1e6), int((at_s + gap_s) * 1e6), False
    for t_us, msg in messages(seed=seed):
        if start_us <= t_us < end_us:
            if not silent:
                silent = True
                rig.settle(0.5)
                time.sleep(gap_s)
            continue
        rig.send(msg)
    rig.settle()
    r = rig.stop()
    alarm = first_attack_alarm(r["alarms"])
    shift_us = start_us if at_s * 1e6 < ATTACK_US < end_us else 0
    return {"gap_s": gap_s, "at_s": at_s, "alive": r["alive"],
            "warned": any("no GNSS or IMU data" in line for line in r["lines"]),
            "back": any("data is back" in line for line in r["lines"]),
            "false_alarms": [a for a in r["alarms"] if a.t_us < ATTACK_US],
            "delay": delay_samples(alarm, max(ATTACK_US, end_us) if shift_us else ATTACK_US),
            "cleared_gnss": [c for c in r["cleared"] if c.sensor == "gnss_pos"],
            "standing": "gnss_pos" in r["excluded"],
            "reinitialised": sum("re-initialis" in line for line in r["lines"]),
            "timeout_s": 5.0}


def silence(args) -> int:
    bad = 0
    print("gap   at      warned  back  false  delay  gnss alarm at the end  cleared by it  re-init  alive")
    for at_s in (10.0, 50.0):
        for gap in args.gaps:
            c = silence_case(gap, at_s, args.seed)
            ok = (c["alive"] and not c["false_alarms"] and c["delay"] is not None and c["delay"] <= 3
                  and c["standing"] and not c["cleared_gnss"] and c["warned"] == (gap > c["timeout_s"])
                  and (c["back"] or not c["warned"]))
            bad += not ok
            print(f"{gap:4.0f}s {at_s:4.0f}s  {str(c['warned']):6s}  {str(c['back']):5s} {len(c['false_alarms']):5d}  "
                  f"{c['delay']!s:>5}  {str(c['standing']):21s}  {len(c['cleared_gnss']):13d}  "
                  f"{c['reinitialised']:7d}  "
                  f"{c['alive']}" + ("" if ok else "   FAILED"))
    print("silence before the attack (from 10 s) and during it (from 50 s, after the alarm); delay: GNSS samples "
          "after the attack's first one")
    # the limit: the attack starts while the link is down longer than monitor.max_gap_s (10 s)
    c = silence_case(20.0, 30.0, args.seed)
    print("the limit: silent from 30 to 50 s, the attack starting at 40 s meanwhile: "
          f"re-initialised {c['reinitialised']}, "
          f"alarm {'after ' + str(c['delay']) + ' samples' if c['delay'] is not None else 'never'}, false alarms "
          f"{len(c['false_alarms'])}, alive {c['alive']} (a new filter starts on the first fix after a long gap: "
          "one already attacked is its reference)")
    return 1 if bad else 0


# -- reboot -----------------------------------------------------------------------------------------

def reboot_case(kind: str, at_s: float, seed: int = 1) -> dict:
    """`reboot`: from at_s on, the autopilot's clock restarts at 3 s (and its frame sequence at 0);
    `wild`: one RAW_IMU at at_s stamped 1000 s ahead, the stream going on as it was."""
    rig = Rig()
    at_us, shift, done = int(at_s * 1e6), 0, False
    for t_us, msg in messages(seed=seed):
        if t_us >= at_us and not done:
            done = True
            if kind == "reboot":
                shift = 3_000_000 - t_us
                rig.settle(0.3)
                rig.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
            elif msg.get_type() == "RAW_IMU":
                rig.send(retimed(msg, 1_000_000_000))
            else:
                done = False
        rig.send(retimed(msg, shift) if shift else msg)
    rig.settle()
    r = rig.stop()
    attack_us = ATTACK_US + shift if at_us < ATTACK_US else ATTACK_US
    alarm = first_attack_alarm(r["alarms"], attack_us if at_us < ATTACK_US else ATTACK_US)
    before = [a for a in r["alarms"] if (a.t_us < at_us if at_us < ATTACK_US else a.t_us < ATTACK_US)
              or (at_us < ATTACK_US and shift and a.t_us < attack_us and a is not alarm)]
    return {"kind": kind, "at_s": at_s, "alive": r["alive"], "delay": delay_samples(alarm, attack_us),
            "false_alarms": before, "standing": "gnss_pos" in r["excluded"],
            "cleared_gnss": [c for c in r["cleared"] if c.sensor == "gnss_pos"],
            "reinitialised": [line for line in r["lines"] if "re-initialis" in line or "alarm stands" in line],
            "skipped": dict(rig.daemon.monitor.skipped)}


def reboot(args) -> int:
    bad = 0
    for kind, at_s in (("reboot", 20.0), ("reboot", 55.0), ("wild", 20.0), ("wild", 55.0)):
        c = reboot_case(kind, at_s, args.seed)
        ok = (c["alive"] and not c["false_alarms"] and c["delay"] is not None and c["delay"] <= 3
              and c["standing"] and not c["cleared_gnss"]
              and (len(c["reinitialised"]) >= 1 if kind == "reboot" else not c["reinitialised"]))
        bad += not ok
        what = "the autopilot reboots" if kind == "reboot" else "one RAW_IMU stamped 1000 s ahead"
        print(f"{what} at {at_s:.0f} s: alarm {c['delay']} samples after the attack, false alarms "
              f"{len(c['false_alarms'])}, GNSS alarm standing at the end {c['standing']}, cleared by the fault "
              f"{len(c['cleared_gnss'])}, warnings about it {len(c['reinitialised'])}, alive {c['alive']}"
              + ("" if ok else "   FAILED"))
        for line in c["reinitialised"][:2]:
            print(f"    guard said: {line}")
        if kind == "wild":
            print(f"    counted: {({k: v for k, v in c['skipped'].items() if v})}")
    return 1 if bad else 0


# -- kill -------------------------------------------------------------------------------------------

def guard_run(mcap: str = "") -> tuple[subprocess.Popen, int]:
    """`guard run` as a process on a free UDP port (logging to `mcap` if given), once it listens."""
    port = free_udp_port()
    command = [sys.executable, "-m", "guard", "run", "--connect", f"udpin:127.0.0.1:{port}"]
    proc = subprocess.Popen(command + (["--mcap", mcap] if mcap else []), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    said = []
    for line in proc.stdout:
        said.append(line)
        if "listening on" in line:
            break
    else:
        raise RuntimeError(f"guard run exited ({proc.wait()}) before listening: {''.join(said)[-2000:]}")
    # read on, so that a daemon saying much never blocks on a full pipe; what it says is kept
    proc.said = said                                          # type: ignore[attr-defined]
    proc.reader = threading.Thread(target=lambda: said.extend(proc.stdout), daemon=True)   # type: ignore
    proc.reader.start()
    return proc, port


def kill_case(at_s: float, workdir: Path, speedup: float, seed: int = 1) -> dict:
    """`guard run --mcap` fed at `speedup` times real time, SIGKILLed at_s seconds of wall clock in;
    then `guard mcap-recover` and the recovered file read back with the mcap library."""
    logdir = workdir / f"kill-{at_s:.2f}"
    logdir.mkdir()
    proc, port = guard_run(str(logdir))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    start, last_t_us, fixes_sent = time.monotonic(), 0, 0
    for t_us, msg in messages(seed=seed):
        wait = start + t_us / 1e6 / speedup - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        if time.monotonic() - start >= at_s:
            break
        sock.sendto(msg.pack(mav), ("127.0.0.1", port))
        last_t_us = t_us
        fixes_sent += msg.get_type() == "GPS_RAW_INT"
    time.sleep(0.05)                            # what is on its way
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    proc.reader.join(timeout=10)
    proc.stdout.close()
    sock.close()
    cut = next(logdir.glob("*.mcap"))
    whole = workdir / f"recovered-{at_s:.2f}.mcap"
    r = subprocess.run([sys.executable, "-m", "guard", "mcap-recover", str(cut), str(whole)],
                       capture_output=True, text=True, timeout=60)
    fixes, alarms, raw = 0, 0, 0
    with open(whole, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            fixes += channel.topic == "/gnss/fix"
            alarms += channel.topic == "/alarms"
            raw += len(message.data) + 31            # a message record's size in a chunk, before compression
    return {"at_s": at_s, "sent_s": last_t_us / 1e6, "fixes_sent": fixes_sent, "fixes": fixes,
            "recover_rc": r.returncode, "alarm_logged": alarms > 0,
            "raw_bytes_per_fix": raw / fixes if fixes else float("inf"),
            "recover": (r.stdout + r.stderr).strip().splitlines()[-1:] or [""]}


def kill(args) -> int:
    rng = random.Random(args.seed)
    chunk_kb = parse({}).log.chunk_kb
    work = Path(tempfile.mkdtemp(prefix="guard-kill-"))
    bad = 0
    try:
        duration = 80.0 / args.speedup
        cases = [kill_case(rng.uniform(0.1 * duration, 0.95 * duration), work, args.speedup, args.seed)
                 for _ in range(args.kills)]
        # what one chunk holds, in seconds of this drive (a kill before the first chunk closed recovers nothing)
        per_fix = sorted(c["raw_bytes_per_fix"] for c in cases if c["fixes"])
        chunk_s = chunk_kb * 1024 / per_fix[len(per_fix) // 2] * GNSS_PERIOD_US / 1e6 if per_fix else float("inf")
        for c in cases:
            # GNSS at 10 Hz: a fix lost is 0.1 s of the vehicle's time lost
            lost_s = max(0, c["fixes_sent"] - c["fixes"]) * GNSS_PERIOD_US / 1e6
            alarm_due = c["sent_s"] > ATTACK_US / 1e6 + 1.0
            ok = c["recover_rc"] == 0 and lost_s <= chunk_s + 1.0 and (c["alarm_logged"] or not alarm_due)
            bad += not ok
            print(f"killed {c['at_s']:4.1f} s in, at vehicle time {c['sent_s']:4.1f} s: {c['fixes']} of "
                  f"{c['fixes_sent']} GNSS fixes recovered, {lost_s:4.1f} s lost, the alarm's record "
                  f"{'kept' if c['alarm_logged'] else 'absent'}{'' if alarm_due else ' (none yet)'}"
                  + ("" if ok else "   FAILED"))
        print(f"one {chunk_kb:.0f} kB chunk (log.chunk_kb) holds {chunk_s:.1f} s of this drive: the most a kill "
              f"may lose; lost at most {max(max(0, c['fixes_sent'] - c['fixes']) for c in cases) / 10:.1f} s "
              f"in {len(cases)} kills")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if bad else 0


# -- disk -------------------------------------------------------------------------------------------

def disk(args) -> int:
    mount = Path(tempfile.mkdtemp(prefix="guard-full-"))
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={args.size_kb}k", "tmpfs", str(mount)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        print(f"faults disk: cannot mount a tmpfs on {mount} (needs root): {r.stderr.strip() or r.returncode}",
              file=sys.stderr)
        mount.rmdir()
        return 2
    try:
        rig = Rig(mcap=str(mount))
        for _, msg in messages(seed=args.seed):
            rig.send(msg)
        rig.settle()
        r = rig.stop()
        lost = [line for line in r["lines"] if "MCAP log lost" in line]
        alarm = first_attack_alarm(r["alarms"])
        for line in lost:
            print(f"    guard said: {line}")
        readable, fixes, out = 0, 0, Path(tempfile.mkdtemp(prefix="guard-recovered-"))
        try:
            for path in sorted(mount.glob("*.mcap")):   # cut by the full disk: made whole elsewhere, then read
                whole = out / path.name
                subprocess.run([sys.executable, "-m", "guard", "mcap-recover", str(path), str(whole)],
                               capture_output=True, timeout=60)
                if whole.is_file():
                    with open(whole, "rb") as f:
                        fixes += sum(channel.topic == "/gnss/fix" for _, channel, _ in make_reader(f).iter_messages())
                    readable += 1
        finally:
            shutil.rmtree(out, ignore_errors=True)
        used = sum(p.stat().st_size for p in mount.glob("*"))
        ok = r["alive"] and delay_samples(alarm) is not None and delay_samples(alarm) <= 3 and 1 <= len(lost) <= 2 \
            and not [a for a in r["alarms"] if a.t_us < ATTACK_US]
        print(f"{args.size_kb} kB disk, {used // 1024} kB written: the alarm {delay_samples(alarm)} samples after the "
              f"attack, false alarms {len([a for a in r['alarms'] if a.t_us < ATTACK_US])}, alive {r['alive']}; "
              f"'MCAP log lost' said {len(lost)} time(s); {readable} file(s) recovered and read back, {fixes} "
              f"GNSS fixes of 801 in them"
              + ("" if ok else "   FAILED"))
        return 0 if ok else 1
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True)
        mount.rmdir()


# -- memory -----------------------------------------------------------------------------------------

def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def memory(args) -> int:
    """`guard run` as a process (its memory alone: the simulator's grows with its record of the drive),
    fed a clean drive of `--minutes`, its resident memory read every minute of the drive."""
    proc, port = guard_run(args.mcap)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    start, series, next_minute = time.monotonic(), [], 0
    for t_us, msg in messages("clean", args.seed, minutes=args.minutes):
        if t_us >= next_minute * 60_000_000:
            series.append((next_minute, rss_mb(proc.pid)))
            print(f"minute {next_minute:3d}: {series[-1][1]:.1f} MB", flush=True)
            next_minute += 1
        wait = start + t_us / 1e6 / args.speedup - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        sock.sendto(msg.pack(mav), ("127.0.0.1", port))
    took = time.monotonic() - start
    time.sleep(2.0)
    series.append((args.minutes, rss_mb(proc.pid)))
    alive = proc.poll() is None
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=30)
    proc.reader.join(timeout=10)                 # to the end of what it said
    proc.stdout.close()
    summary = next((line for line in proc.said if "stopped after" in line), "")
    alarms = int(summary.split(" alarm(s)")[0].rsplit(" ", 1)[-1]) if " alarm(s)" in summary else -1
    sock.close()
    base = next((mb for minute, mb in series if minute >= 5), series[0][1])
    growth = series[-1][1] - base
    ok = alive and growth <= args.bound_mb and alarms == 0
    print(f"{args.minutes:g} minutes of driving, paced at {args.speedup:g}x real time, in {took:.0f} s: the daemon's "
          f"resident memory {series[0][1]:.1f} MB at the start, {base:.1f} MB at minute 5, {series[-1][1]:.1f} MB at "
          f"the end (growth {growth:+.1f} MB, bound {args.bound_mb:g}); alarms {alarms}, alive {alive}"
          + ("" if ok else "   FAILED"))
    print(summary)
    if args.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(7, 3))
        ax.plot([m for m, _ in series], [mb for _, mb in series], marker=".")
        ax.set_xlabel("minutes of driving")
        ax.set_ylabel("resident memory (MB)")
        ax.set_ylim(0, max(mb for _, mb in series) * 1.2)
        ax.set_title(f"guard run over {args.minutes:g} minutes of a clean drive")
        fig.tight_layout()
        fig.savefig(args.plot)
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=1)
    sub = p.add_subparsers(dest="campaign", required=True)
    s = sub.add_parser("silence", help="the link silent, then back")
    s.add_argument("--gaps", type=float, nargs="+", default=[2.0, 8.0, 20.0], help="seconds of silence")
    sub.add_parser("reboot", help="the autopilot reboots; a lone frame with a wild time stamp")
    k = sub.add_parser("kill", help="SIGKILL at random moments, then mcap-recover")
    k.add_argument("--kills", type=int, default=10)
    k.add_argument("--speedup", type=float, default=4.0, help="the scenario's pace (default 4x real time)")
    d = sub.add_parser("disk", help="the log directory on a small tmpfs that fills (needs root)")
    d.add_argument("--size-kb", type=int, default=256)
    m = sub.add_parser("memory", help="resident memory over a long drive")
    m.add_argument("--minutes", type=float, default=60.0)
    m.add_argument("--speedup", type=float, default=1.0)
    m.add_argument("--bound-mb", type=float, default=5.0, help="the growth allowed from minute 5 on")
    m.add_argument("--mcap", default="", help="log to this directory meanwhile")
    m.add_argument("--plot", default="", help="write the series as a figure (.png)")
    args = p.parse_args(argv)
    return {"silence": silence, "reboot": reboot, "kill": kill, "disk": disk, "memory": memory}[args.campaign](args)


if __name__ == "__main__":
    sys.exit(main())
