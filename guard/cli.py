"""The `guard` command: run, replay, tune, sim, demo, config, mcap-recover.

Errors a user can fix (a missing file, a bad config key, an unknown scenario, a link that cannot be
opened) are one line on stderr and a non-zero exit status.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from guard import DEFAULT_CONFIG_PATH as DEFAULT_CONFIG
from guard import __version__
from guard.errors import ConfigError, GuardError

EX_CONFIG = 78     # sysexits' configuration error: the systemd unit does not restart on it (it would not mend)


def _replay(args) -> int:
    from dataclasses import replace
    from guard.config import load
    from guard.runtime.replay_command import ONE_LOG_OPTIONS, replay_log, replay_logs, unreadable_folder
    from guard.sources import find_logs
    logs = find_logs(args.logs)
    given = [f"--{o}" for o in ONE_LOG_OPTIONS if getattr(args, o)]
    if len(logs) > 1 and given:
        raise GuardError(f"{', '.join(given)}: one log's output, and {len(logs)} logs are given: replay them one at a time")
    cfg = load(args.config)
    if args.detector:
        cfg = replace(cfg, monitor=replace(cfg.monitor, detector=replace(cfg.monitor.detector, name=args.detector)))
    cfg = _with_system_id(cfg, args.system_id)
    if len(logs) == 1:          # one log, however named (a folder that holds one): as a log given alone
        if error := unreadable_folder(logs[0]):
            raise GuardError(error)
        args.file = logs[0]
        return replay_log(args, cfg)
    from guard.runtime.tune import default_jobs
    return replay_logs(logs, cfg, args.imu, args.gnss, args.jobs or default_jobs())


def _run(args) -> int:
    from guard.config import load
    from guard.runtime.daemon import Daemon
    cfg = _with_system_id(load(args.config), args.system_id)
    return Daemon(cfg, connect=args.connect, mcap=args.mcap).run()


def _config(args) -> int:
    """The configuration in effect: the file's keys, the defaults for the rest, the overrides."""
    from dataclasses import replace
    from guard.config import default_path, dump, load, read
    path = args.config or default_path()
    cfg = load(path)
    given = {f"{sec}.{key}" for sec, tab in read(path)[0].items() if isinstance(tab, dict) for key in tab} \
        if path else set()
    overrides = []
    if args.connect:
        cfg, _ = (replace(cfg, link=replace(cfg.link, connect=args.connect)),
                  overrides.append("link.connect (--connect)"))
    if args.mcap is not None:
        cfg, _ = replace(cfg, log=replace(cfg.log, mcap=args.mcap)), overrides.append("log.mcap (--mcap)")
    if args.system_id is not None:
        cfg, _ = _with_system_id(cfg, args.system_id), overrides.append("link.system_id (--system-id)")
    print(f"# guard {__version__}: the configuration in effect")
    print(f"# file: {path or 'none (no --config, and no ' + DEFAULT_CONFIG + ')'}")
    print(f"# from the file: {', '.join(sorted(given)) or 'nothing'}; every other key is its default")
    print(f"# from the command line: {', '.join(overrides) or 'nothing'}")
    print(dump(cfg), end="")
    return 0


def _sim(args) -> int:
    from guard_sim import scenario
    from guard_sim.run import run
    try:
        sc = scenario.load(args.scenario)
    except scenario.ScenarioError as e:
        raise GuardError(str(e)) from None
    if not (args.tlog or args.bin or args.ulg or args.out or args.can):
        raise GuardError("guard sim: give --tlog FILE, --bin FILE, --ulg FILE, --out URL or --can URL")
    can = None
    if args.can:
        from guard_sim.canbus import CanPublisher
        try:
            can = CanPublisher(args.can)
        except Exception as e:      # python-can raises many kinds
            reason = str(e).removeprefix(f"cannot open CAN bus {args.can.split(':', 1)[-1]}: ")
            raise GuardError(f"cannot open CAN bus {args.can}: {reason}") from None

    def show(msg) -> None:
        names = {2: "CRITICAL", 4: "WARNING", 5: "NOTICE", 6: "INFO"}
        print(f"[ground station] {names.get(msg.severity, msg.severity)}: {msg.text}", flush=True)

    def asked(name: str, interval_us: int) -> None:
        rate = "off" if interval_us < 0 else "the port's default" if interval_us == 0 else f"{1e6 / interval_us:g} Hz"
        print(f"[autopilot] {name} at {rate}, as asked", flush=True)

    try:
        truth = run(sc, args.seed, tlog=args.tlog, out=args.out, speedup=args.speedup, fast=args.fast,
                    on_statustext=show, can=can, bin=args.bin, ulg=args.ulg, autopilot=args.autopilot,
                    stream_hz=args.stream_hz, on_request=asked)
    finally:
        if can:
            can.close()
    where = ", ".join(w for w in (args.tlog, args.bin, args.ulg, args.out, args.can) if w)
    print(f"sim: scenario {sc.name}, seed {args.seed}, {sc.duration_s:.0f} s -> {where}", file=sys.stderr)
    return 0 if truth else 1


def _demo(args) -> int:
    from guard.runtime.demo import demo
    return demo(args.scenario, args.seed, args.speedup)


def _recover(args) -> int:
    import os
    from guard.sinks.mcap import recover
    if os.path.exists(args.dst):
        if os.path.exists(args.src) and os.path.samefile(args.src, args.dst):
            raise GuardError(f"mcap-recover: {args.dst} is the log to recover: write the copy elsewhere")
        if not args.force:
            raise GuardError(f"mcap-recover: {args.dst} exists: give another name, or --force to overwrite it")
    messages, channels = recover(args.src, args.dst)
    print(f"{args.dst}: recovered {messages} messages on {channels} channels")
    return 0


def _tune(args) -> int:
    from guard.config import load
    from guard.runtime.tune import default_jobs, tune, write_profile
    from guard.sources import find_logs
    from guard.runtime.replay_command import unreadable_folder
    logs = [log for given in args.logs for log in (find_logs([given]) if Path(given).is_dir() else [given])]
    for log in logs:
        if error := unreadable_folder(log):
            raise GuardError(error)
    profile, cfg = tune(logs, load(args.config), jobs=args.jobs or default_jobs())
    write_profile(profile, args.out, logs, cfg)
    changed = ", ".join(f"{k} = {v:g}" for table in profile.values() for k, v in table.items()) or "nothing"
    print(f"guard tune: {args.out}: {changed}")
    return 0


def _with_system_id(cfg, system_id: int | None):
    """cfg with --system-id in link.system_id, where it was given."""
    from dataclasses import replace
    return cfg if system_id is None else replace(cfg, link=replace(cfg.link, system_id=system_id))


def _positive_int(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of 1 or more")
    return int(text)


def _system_id(text: str) -> int:
    if not text.isdigit() or int(text) > 255:
        raise argparse.ArgumentTypeError(f"{text!r} is not a MAVLink system id (0..255)")
    return int(text)


class Defaults(argparse.HelpFormatter):
    """Help that says an option's default where it has one (not for flags, nor where the help says it)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default not in (None, False, argparse.SUPPRESS) and "default" not in text:
            text += " (default: %(default)s)"
        return text


RUN_EXAMPLES = """examples:
  guard run                                            # link.connect of the config (default udpin:0.0.0.0:14550)
  guard run --connect udpin:0.0.0.0:14550              # a mavlink-router or MAVProxy output to this port
  guard run --connect /dev/ttyAMA0,921600              # the flight controller's companion (TELEM2) port
  guard run --connect tcp:127.0.0.1:5760               # ArduPilot SITL
  guard run --connect can:socketcan:can0               # DroneCAN GNSS and IMU on the vehicle's CAN bus
  guard run --config my-rover.toml --mcap /var/log/guard
  guard config --config my-rover.toml                  # what that would run with"""


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="guard", description="Detect attacks on a vehicle's navigation sensors.")
    p.add_argument("--version", action="version", version=f"guard {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    # -v after the subcommand too (guard run -v): its default must not undo one given before it
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    fmt = Defaults

    def command(name: str, **kw):
        return sub.add_parser(name, parents=[common], formatter_class=kw.pop("formatter_class", fmt), **kw)

    r = command("run", help="the daemon: read a live link, alarm on it, log to MCAP",
                description="Read GPS_RAW_INT, RAW_IMU (ArduPilot) or HIGHRES_IMU (PX4) and ATTITUDE from a live "
                "MAVLink link (or DroneCAN), "
                "run the detector, send the alarms back as STATUSTEXT and log to MCAP.",
                epilog=RUN_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    r.add_argument("--connect", help="udpin:HOST:PORT, udpout:HOST:PORT, udpbcast:ADDRESS:PORT, tcp:HOST:PORT, "
                   "tcpin:HOST:PORT, a serial DEVICE[,BAUD] (default 115200 baud) or can:INTERFACE:CHANNEL; "
                   "default: link.connect of the config (udpin:0.0.0.0:14550)")
    r.add_argument("--config", help=f"TOML config file; default: {DEFAULT_CONFIG} if it exists, else the built-in "
                   "defaults (guard config prints them)")
    r.add_argument("--mcap", help="MCAP log file or directory; default: log.mcap of the config (none)")
    r.add_argument("--system-id", type=_system_id, help="the autopilot's MAVLink system id (its SYSID_THISMAV); "
                   "default: link.system_id of the config (1); 0 reads every system")
    r.set_defaults(func=_run)

    r = command("config", help="print the configuration in effect (file, defaults, overrides) as TOML",
                description="Print the configuration guard run would use: the file's keys, every other key "
                "at its default, and the command line's overrides, as a TOML file --config reads back.")
    r.add_argument("--config", help=f"TOML config file (default: {DEFAULT_CONFIG} if it exists)")
    r.add_argument("--connect", help="as guard run --connect")
    r.add_argument("--mcap", help="as guard run --mcap")
    r.add_argument("--system-id", type=_system_id, help="as guard run --system-id")
    r.set_defaults(func=_config)

    r = command("replay", help="run logs through the detector offline (tlog, DataFlash .bin, ULog .ulg)",
                description="Replay logs through the detector and say what each one showed. Several logs, or "
                "folders of them (an SD card's), are replayed on --jobs processes with a closing count; "
                "--report, --plot and --mcap take one log. Example: guard replay flight.bin --plot flight.png")
    r.add_argument("logs", nargs="+", metavar="LOG",
                   help="a log: .tlog (MAVLink), .bin (ArduPilot DataFlash) or .ulg (PX4 ULog), recognised by its "
                   "content; or a folder of them")
    r.add_argument("--imu", type=int, metavar="N",
                   help="the IMU instance to read, in a log with several (default: the primary)")
    r.add_argument("--gnss", type=int, metavar="N", help="the GNSS receiver to read, in a log with several")
    r.add_argument("--config", help="TOML config file")
    r.add_argument("--detector", choices=["cusum", "paper", "gate", "chi2"], help="override detector.name")
    r.add_argument("--system-id", type=_system_id, help="the autopilot's MAVLink system id (overrides link.system_id; "
                                                 "0: every system)")
    r.add_argument("--report", help="write the JSON report here ('-' for stdout)")
    r.add_argument("--plot", help="write the three-panel figure here (.png)")
    r.add_argument("--mcap", help="write an MCAP log here")
    r.add_argument("--jobs", type=_positive_int, metavar="N",
                   help="several logs: replay them on N processes (default: every core)")
    r.set_defaults(func=_replay)

    r = command("tune", help="fit the noise model to your vehicle's clean logs; write a profile for --config",
                       description="Fit guard's noise model (GNSS, IMU and magnetometer noise, the receiver's "
                       "latency, the compass's offset) to clean logs of one vehicle, print the margins it "
                       "leaves, and write a TOML profile. Example: guard tune flight1.bin flight2.bin "
                       "--out my-rover.toml, then guard run --config my-rover.toml")
    r.add_argument("logs", nargs="+", help="clean logs of the vehicle (.tlog, .bin, .ulg), without an attack, "
                   "or folders of them")
    r.add_argument("--out", default="guard-profile.toml", help="the profile to write (default: guard-profile.toml)")
    r.add_argument("--config", help="the config to start from (default: guard's defaults)")
    r.add_argument("--jobs", type=_positive_int, metavar="N",
                   help="replay the logs on N processes (default: every core; the profile is the same)")
    r.set_defaults(func=_tune)

    r = command("sim", help="the simulator: a vehicle speaking MAVLink (and DroneCAN)")
    r.add_argument("--scenario", default="paper", help="a shipped scenario (paper, clean, step_east, ramp_north, "
                   "gyro_bias, accel_bias, freeze, spoof, wandering_compass) or a scenario TOML file")
    r.add_argument("--seed", type=int, default=1, help="the simulator's random seed (noise, attack phases)")
    r.add_argument("--tlog", help="write a tlog (and NAME.truth.json beside it)")
    r.add_argument("--bin", help="write the run as an ArduPilot DataFlash log too (and its truth beside it)")
    r.add_argument("--ulg", help="write the run as a PX4 ULog too (and its truth beside it)")
    r.add_argument("--out", help="send live MAVLink to this pymavlink URL, e.g. udpout:127.0.0.1:14550")
    r.add_argument("--can", help="publish DroneCAN on this bus, e.g. can:virtual:bus0")
    r.add_argument("--speedup", type=float, default=1.0, help="live output at X times real time")
    r.add_argument("--fast", action="store_true", help="live output as fast as possible (no pacing)")
    r.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot",
                   help="how the tlog and the live link send the IMU: ardupilot, RAW_IMU (default); px4, "
                        "HIGHRES_IMU, as PX4's onboard link does")
    r.add_argument("--stream-hz", type=float, default=0.0,
                   help="live: send GPS_RAW_INT and the IMU at most this often until asked for more "
                        "(MAV_CMD_SET_MESSAGE_INTERVAL), as an autopilot's port at its default rates; 0: every sample")
    r.set_defaults(func=_sim)

    r = command("demo", help="simulator and daemon on UDP loopback: watch the attack being caught")
    r.add_argument("--scenario", default="paper", help="scenario name or TOML file, as guard sim")
    r.add_argument("--seed", type=int, default=1, help="the simulator's random seed (noise, attack phases)")
    r.add_argument("--speedup", type=float, default=4.0, help="times real time")
    r.set_defaults(func=_demo)

    r = command("mcap-recover", help="make a truncated MCAP log whole (after a crash)",
                description="Copy every complete record of a cut MCAP log (a crash, a power loss) into a new, "
                "finished file. Example: guard mcap-recover guard-20261123-101500.mcap recovered.mcap")
    r.add_argument("src", help="the cut log (left as it is)")
    r.add_argument("dst", help="the file to write (not the cut log itself)")
    r.add_argument("--force", action="store_true", help="overwrite dst if it exists")
    r.set_defaults(func=_recover)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(name)s: %(levelname)s: %(message)s", stream=sys.stderr)
    logging.getLogger("dronecan").setLevel(logging.WARNING)     # its import says which drivers it lacks
    try:
        return args.func(args)
    except ConfigError as e:
        print(f"guard: error: {e}", file=sys.stderr)
        return EX_CONFIG
    except GuardError as e:
        print(f"guard: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
