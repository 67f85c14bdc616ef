"""Every log in some folders replayed through guard: a line per log (its format, length, alarms by
sensor, the largest statistic/threshold per sensor, how far the estimate stood from the fixes, the
receiver's own largest jump between fixes, and guard replay's line on a compass that reads off by
heading, guard.runtime.deviation), then the totals, with how many of the logs guard run would warn
of such a compass on (its LiveCheck, played through each log beside the replay), and of levelled
accelerometers that wander from the GNSS (guard.runtime.agreement.LiveWander, likewise). For logs
of flights with no attack, every alarm is a false one or a fault in the vehicle: this is how guard is
measured on real vehicles it was never tuned on.

    python tools/real_logs.py ../shared/data/real LOGS_DIR ...          # the defaults
    python tools/real_logs.py LOGS_DIR --set monitor.max_wander_factor=1   # a config key changed
    python tools/real_logs.py LOGS_DIR --config my-vehicle.toml --json out/real.json
    python tools/real_logs.py LOGS_DIR --attack step:2 --attack step:10 --attack ramp:0.3
    python tools/real_logs.py LOGS_DIR --attack gyro:0.05 --attack accel:0.5
    python tools/real_logs.py LOGS_DIR --autopilot     # and how many GNSS velocity alarms the autopilot saw too

`--attack` writes an attack into each flight's own fixes, from its fix at 30, 50 and 70 % of them
(each a run of its own), and says how often and how fast it was caught: a GNSS alarm within
WINDOW_S of the onset, beside how often the same window held a GNSS alarm without the attack (the
chance of it). `step:M` moves the position M metres north, `ramp:V` drifts it north at V m/s; the
velocity is left as the receiver gave it (a naive spoof). `gyro:W` adds W rad/s to the gyro's z axis
(a bias on the yaw rate, as an injection into the IMU would), `accel:A` A m/s^2 to the
accelerometer's x axis (forward): caught by an alarm on any sensor within WINDOW_S, as the heading
or velocity it bends shows in the compass's test or the GNSS velocity's, beside the chance of an
alarm on any sensor in the same window. Each attack's run replays its log only to END_MARGIN_S
after its window (what follows cannot change what came within it). This is detection
measured on real vehicles' noise, which the simulator's figures are not.

A log is .tlog, .bin or .ulg, recognised by its content; a file that is none of them is listed with
the reason and skipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import tomllib                                       # noqa: E402

from guard.config import parse, read                 # noqa: E402
from guard.errors import GuardError                  # noqa: E402
from guard.core.aiding.motors import OPEN_S          # noqa: E402
from guard.core.geo import LocalFrame                # noqa: E402
from guard.model.samples import GnssFix, ImuSample   # noqa: E402
from guard.runtime.agreement import LiveWander                                         # noqa: E402
from guard.runtime.position_wander import LivePositionWander, PositionWander, beyond_tune   # noqa: E402
from guard.runtime.deviation import SAY_DEG, Headings, LiveCheck, compass_fits, said   # noqa: E402
from guard.runtime.replay import replay              # noqa: E402
from guard.sources import find_logs                  # noqa: E402
import pymap3d                                       # noqa: E402
from tools.autopilot_view import SAW_TOP, read_log, report_time_as_logged, saw_too, view   # noqa: E402
from tools.autopilot_view import WINDOW_S as AUTOPILOT_WINDOW_S                 # noqa: E402

def logs_in(paths: list[str]) -> list[str]:
    """The logs in each folder and the folders within it, and each single file, as `guard replay`
    finds them (guard.sources.find_logs); a GuardError names one missing, or a folder that holds no log."""
    return find_logs(paths)


def each_log(doc: str, measure, show, argv=None) -> list[dict] | int:
    """The command line of a tool that measures each log on its own (course_hold, compass_deviation):
    LOGS (folders or files), --jobs, --json. Each log's result dict (with "log", or "error" where it
    could not be read) is shown as it comes, and all of them written to --json; a folder or file that
    is not there is said and 2 returned instead."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", help="folders of logs, or single logs")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", help="write every log's result here")
    args = ap.parse_args(argv)
    try:
        logs = logs_in(args.logs)
    except GuardError as e:
        print(f"guard: {e}", file=sys.stderr)
        return 2
    results = []
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        for r in ex.map(measure, logs):
            results.append(r)
            show(r)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return results


def config_of(path: str | None, sets: tuple[str, ...]):
    """The config file's keys (none: the defaults), then each "section.key=TOML value" over them."""
    table: dict = read(path)[0] if path else {}
    for item in sets:
        key, _, value = item.partition("=")
        section, _, field = key.strip().partition(".")
        try:
            table.setdefault(section, {})[field] = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError as e:
            raise GuardError(f"--set {item}: not a TOML value ({e})") from None
    return parse(table, f"{path or 'defaults'} {' '.join(sets)}".strip())


ONSETS = (0.3, 0.5, 0.7)        # at which share of a log's fixes an attack starts, one run each
# an alarm this long after the onset is the attack caught
WINDOW_S = {"step": 5.0, "ramp": 30.0, "gyro": 10.0, "accel": 10.0}
END_MARGIN_S = 2.0   # an attack's run replays its log to this long after its window (attack())
IMU_ATTACKS = ("gyro", "accel")  # written into the IMU, caught by an alarm on any sensor
RECEIVER = {"gnss_pos", "gnss_vel"}


class Span:
    """The times of a run's fixes, and the receiver's own largest jump: how far a fix lies from where
    the last one and the two velocities put it (|dp - (v + v') dt / 2|, fixes at most JUMP_DT_S apart)."""

    JUMP_DT_S = 1.5

    def __init__(self):
        self.fixes: list[int] = []
        self.frame = None
        self.last = None
        self.jump = 0.0

    def on_sample(self, s) -> None:
        if not (isinstance(s, GnssFix) and s.fix_ok):
            return
        self.fixes.append(s.t_us)
        if s.vel_n_mps is None:
            return
        self.frame = self.frame or LocalFrame(s.lat_deg, s.lon_deg, s.alt_m)
        e, n = self.frame.to_en(s.lat_deg, s.lon_deg)
        if self.last and 0 < s.t_us - self.last[0] <= self.JUMP_DT_S * 1e6:
            t, e0, n0, ve0, vn0 = self.last
            dt = (s.t_us - t) / 1e6
            self.jump = max(self.jump, math.hypot(e - e0 - 0.5 * (s.vel_e_mps + ve0) * dt,
                                                  n - n0 - 0.5 * (s.vel_n_mps + vn0) * dt))
        self.last = (s.t_us, e, n, s.vel_e_mps, s.vel_n_mps)

    def on_events(self, events) -> None:
        pass

    def close(self) -> None:
        pass


def attack(kind: str, size: float, onset_us: int, until_us: int | None = None):
    """The sample stream with the attack written into it from onset_us on: into its fixes (step, ramp)
    or its IMU (gyro, accel). A log whose IMU is not integrated (telemetry at 1 to 4 Hz) cannot
    catch an IMU attack: its runs count only the alarms that came by chance. `until_us`: the stream
    ends at its first sample stamped within a second after until_us + END_MARGIN_S (the core is
    causal: what follows the window cannot change whether, or when, the attack was caught within
    it; a run then costs the log up to there). The margin lets a fix sent late, after IMU samples
    stamped past it (a tlog's receiver latency), still come; a sample stamped further on is a
    corrupt or far-off one, which the core counts and skips, and does not end the stream."""
    def north(fix: GnssFix, dn: float) -> GnssFix:
        lat, lon, _ = pymap3d.enu2geodetic(0.0, dn, 0.0, fix.lat_deg, fix.lon_deg, fix.alt_m)
        return dataclasses.replace(fix, lat_deg=float(lat), lon_deg=float(lon))

    def inject(samples):
        for s in samples:
            if until_us is not None and 0 < getattr(s, "t_us", 0) - until_us - END_MARGIN_S * 1e6 <= 1e6:
                return
            if kind in IMU_ATTACKS and isinstance(s, ImuSample) and s.t_us >= onset_us:
                s = dataclasses.replace(s, gyro_z_radps=s.gyro_z_radps + size) if kind == "gyro" else \
                    dataclasses.replace(s, acc_x_mps2=s.acc_x_mps2 + size)
            elif kind not in IMU_ATTACKS and isinstance(s, GnssFix) and s.fix_ok and s.t_us >= onset_us:
                s = north(s, size if kind == "step" else size * (s.t_us - onset_us) / 1e6)
            yield s
    return inject


def caught(alarms: list[dict], onset_us: int, window_s: float, any_sensor: bool = False) -> float | None:
    """The delay (s) of the first GNSS alarm (with any_sensor, of any sensor) within window_s of the
    onset; None: none."""
    for a in alarms:
        if (any_sensor or a["sensor"] in RECEIVER) and onset_us <= a["time_usec"] <= onset_us + window_s * 1e6:
            return (a["time_usec"] - onset_us) / 1e6
    return None


def autopilot_saw(path: str, report: dict) -> list[int] | str:
    """[k, n]: of the n GNSS velocity alarms the autopilot's own EKF could be asked about (its innovations
    in the log there), k it saw too (tools/autopilot_view.py, `saw_too`); or why it could not be read."""
    try:
        data = read_log(path, report["format"])
    except Exception as e:          # noqa: BLE001 - pymavlink and pyulog raise what they raise on a corrupt file
        return f"the autopilot's innovations could not be read ({type(e).__name__}: {e})"
    clock = report.get("clock")
    said = [saw_too(view(data, report_time_as_logged(a["time_usec"], clock) / 1e6, AUTOPILOT_WINDOW_S), a)
            for a in report["alarms"] if a["sensor"] == "gnss_vel"]
    return [sum(x is True for x in said), sum(x is not None for x in said)]


def since_boot(fixes: list[int], t_us: int) -> float | None:
    """Seconds from the first fix on t_us's clock (after the last reboot before it: a fix more than a second
    before the one ahead of it) to t_us; None before any."""
    start = None
    for i, t in enumerate(fixes):
        if t > t_us:
            break
        if i == 0 or t < fixes[i - 1] - 1_000_000:
            start = t
    return None if start is None else round((t_us - start) / 1e6, 1)


def after_motors(report: dict) -> list[float | None]:
    """Each new alarm's time (s) after the latest motors' start heard in the IMU before it (None: none
    was heard before it): how many alarms the take-off brings (guard.core.aiding.motors)."""
    starts = [n["time_usec"] for n in report["notices"] if n["text"].startswith("the motors started")]
    out = []
    for a in report["alarms"]:
        if not a["standing"]:
            before = [a["time_usec"] - t for t in starts if t <= a["time_usec"]]
            out.append(round(min(before) / 1e6, 1) if before else None)
    return out


def one(job: tuple[str, str | None, tuple[str, ...], tuple[str, ...], bool]) -> dict:
    path, config, sets, attacks, ask = job
    span = Span()
    try:
        cfg = config_of(config, sets)
        headings = Headings(cfg=cfg.monitor)
        live: list[str] = []                                # what guard run would say of the compass
        check = LiveCheck(live.append, cfg.monitor)
        wander: list[str] = []                              # ... and of the accelerometers' wander
        wanders = LiveWander(wander.append)
        position: list[str] = []                            # ... and of the receiver's position
        positions = LivePositionWander(position.append, cfg.monitor.filter)
        receiver = PositionWander(cfg.monitor.filter)       # the whole log's, as guard replay measures it
        r = replay(path, cfg, listeners=[span, headings, check, wanders, positions, receiver])
    except GuardError as e:
        return {"log": path, "error": str(e)}
    iron, before, first_s = compass_fits(headings, r)       # as guard replay fits it
    alarms = Counter(str(a["sensor"]) for a in r["alarms"])
    out = {"log": path, "format": r["format"], "duration_s": r["duration_s"], "alarms": dict(alarms),
           "n_alarms": sum(alarms.values()),
           "n_standing": sum(1 for a in r["alarms"] if a["standing"]), "peak_ratio": r["peak_ratio"],
           "estimate_to_fix_m": r["estimate_to_fix_m"],
           "warnings": [n["text"] for n in r["notices"] if n["level"] == "warning"], "attacks": {},
           "receiver_jump_m": round(span.jump, 2), "new_after_motors_s": after_motors(r),
           "receiver_beyond_tune": beyond_tune(receiver.measure()),
           "compass_deviation": {**iron, **({"before_first_alarm": before} if before else {})},
           "compass_said": said(iron, before, first_s),
           "compass_said_live": None if not live else {
               "line": live[0], "time_usec": check.said_us,
               "at_first_alarm": check.said_us == min((a["time_usec"] for a in r["alarms"] if a["sensor"] == "mag"),
                                                      default=None)},
           "wander_said_live": None if not wander else {
               "line": wander[0], "after_first_fix_s": since_boot(span.fixes, wanders.said_us)},
           "position_said_live": None if not position else {
               "line": position[0], "after_first_fix_s": since_boot(span.fixes, positions.said_us)}}
    if ask and r["format"] in ("dataflash", "ulog"):
        out["autopilot_saw"] = autopilot_saw(path, r)
    for spec in attacks:
        kind, size = spec.split(":")
        runs, imu = [], kind in IMU_ATTACKS
        for at in ONSETS:
            onset = span.fixes[int(at * (len(span.fixes) - 1))]
            hit = replay(path, cfg, inject=attack(kind, float(size), onset, onset + int(WINDOW_S[kind] * 1e6)))
            runs.append({"onset_us": onset, "delay_s": caught(hit["alarms"], onset, WINDOW_S[kind], imu),
                         "by_chance_s": caught(r["alarms"], onset, WINDOW_S[kind], imu)})
        out["attacks"][spec] = runs
    return out


def said_live(results: list[dict], key: str, what: str) -> str | None:
    """The summary's line of what guard run would say once (`key` of each result): on how many logs, and
    how long after the first fix on its clock."""
    heard = [r[key] for r in results if r.get(key)]
    if not heard:
        return None
    after = sorted(x["after_first_fix_s"] for x in heard if x["after_first_fix_s"] is not None)
    when = f" ({after[0] / 60:.1f} to {after[-1] / 60:.1f} min after the first fix on its clock, median " \
        f"{after[len(after) // 2] / 60:.1f})" if after else ""
    return f"guard run would say {what} on {len(heard)}{when}"


def attack_spec(text: str) -> str:
    kind, _, size = text.partition(":")
    try:
        ok = kind in WINDOW_S and float(size) > 0.0
    except ValueError:
        ok = False
    if not ok:
        raise argparse.ArgumentTypeError(f"{text!r}: expected step:METRES, ramp:METRES_PER_S, gyro:RAD_PER_S or "
                                         "accel:METRES_PER_S2, a positive number")
    return text


def attack_lines(results: list[dict], attacks: list[str]) -> list[str]:
    """A line per attack: how often and how fast it was caught over every log and onset."""
    lines = [f"attacks written into each flight from its fix at {', '.join(f'{a:.0%}' for a in ONSETS)} "
             "of them (into the fixes north, the velocity untouched; into the gyro's z axis; into the "
             "accelerometer's x axis):"]
    for spec in attacks:
        runs = [run for r in results if "error" not in r for run in r["attacks"][spec]]
        delays = sorted(run["delay_s"] for run in runs if run["delay_s"] is not None)
        chance = sum(run["by_chance_s"] is not None for run in runs)
        kind, size = spec.split(":")
        what = {"step": f"step {float(size):g} m", "ramp": f"ramp {float(size):g} m/s",
                "gyro": f"gyro bias {float(size):g} rad/s", "accel": f"accelerometer bias {float(size):g} m/s2"}[kind]
        which = "any" if kind in IMU_ATTACKS else "a GNSS"
        line = f"  {what}: caught within {WINDOW_S[kind]:g} s in {len(delays)} of {len(runs)} runs " \
               f"({which} alarm in the same window without the attack: {chance})"
        if delays:
            p95 = delays[min(len(delays) - 1, round(0.95 * (len(delays) - 1)))]
            line += f"; delay median {statistics.median(delays):.1f} s, 95th percentile {p95:.1f} s"
            if kind == "ramp":
                line += f" ({float(size) * statistics.median(delays):.1f} m off at the median)"
        lines.append(line)
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", help="folders of logs (or single logs)")
    ap.add_argument("--config", help="TOML config file")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="a config key changed")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", help="write every log's result here")
    ap.add_argument("--attack", action="append", default=[], type=attack_spec, metavar="step:M|ramp:V|gyro:W|accel:A",
                    help="also run each log with this attack written into it (repeatable)")
    ap.add_argument("--autopilot", action="store_true",
                    help="also ask each DataFlash and ULog log's own EKF about guard's GNSS velocity alarms "
                         "(tools/autopilot_view.py): how many it saw too")
    args = ap.parse_args(argv)
    try:                                            # a bad key or file, said before any log runs
        config_of(args.config, tuple(args.set))
        logs = logs_in(args.folders)
    except GuardError as e:
        print(f"guard: {e}", file=sys.stderr)
        return 2
    jobs = [(p, args.config, tuple(args.set), tuple(args.attack), args.autopilot) for p in logs]
    results, total, hours, fixes, far_fixes, saw = [], Counter(), 0.0, 0, 0.0, [0, 0]
    fused_fixes, fused_far, fused_max = 0, 0.0, 0.0     # the same of the fixes whose position was fused
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        for r in ex.map(one, jobs):
            results.append(r)
            name = Path(r["log"]).name
            if "error" in r:
                print(f"{name}: skipped: {r['error']}")
                continue
            total.update(r["alarms"])
            hours += r["duration_s"] / 3600.0
            peaks = " ".join(f"{s} {v:.2f}" for s, v in sorted(r["peak_ratio"].items()))
            by = ", ".join(f"{s} {n}" for s, n in sorted(r["alarms"].items())) or "none"
            gap = r["estimate_to_fix_m"]
            far = gap["share_over_5"]
            fixes += gap["fixes"]
            far_fixes += far * gap["fixes"]
            fused_fixes += gap["fused"]["fixes"]
            fused_far += gap["fused"]["share_over_5"] * gap["fused"]["fixes"]
            fused_max = max(fused_max, gap["fused"]["max"])
            again = f"; {r['n_standing']} a standing alarm again" if r["n_standing"] else ""
            asked = r.get("autopilot_saw")
            if isinstance(asked, list):
                saw = [saw[0] + asked[0], saw[1] + asked[1]]
                asked = f"; the autopilot's EKF saw {asked[0]} of {asked[1]} GNSS velocity alarms too"
            elif asked:
                asked = f"; {asked}"
            off = f"; {r['compass_said']}" if r["compass_said"] else ""
            print(f"{name}: {r['format']}, {r['duration_s']:.0f} s; alarms {r['n_alarms']} ({by}{again}); "
                  f"peaks {peaks}; "
                  f"estimate from the fixes {gap['max']:.1f} m at most, over 5 m at {100 * far:.1f} %; "
                  f"the receiver's own largest jump {r['receiver_jump_m']:.2f} m{off}{asked or ''}")
    n = sum(1 for r in results if "error" not in r)
    quiet = sum(1 for r in results if r.get("n_alarms") == 0)
    by = ", ".join(f"{s} {k}" for s, k in sorted(total.items())) or "none"
    standing = sum(r.get("n_standing", 0) for r in results)
    print(f"{n} logs, {hours:.2f} h: {sum(total.values())} alarms ({by}); {standing} of them a standing "
          f"alarm again; {quiet} logs without one; "
          f"the estimate over 5 m from the fix at {100 * far_fixes / max(fixes, 1):.1f} % of {fixes} fixes; "
          f"at {100 * fused_far / max(fused_fixes, 1):.1f} % of the {fused_fixes} fused ({fused_max:.1f} m at most), "
          f"the rest excluded by an alarm")
    faulty = [r for r in results if r.get("receiver_beyond_tune")]
    if faulty:
        named = ", ".join(f"{Path(r['log']).parent.name}/{Path(r['log']).name}" for r in faulty)
        print(f"guard replay says the receiver's position wanders past the largest walk guard tune fits (a fault or "
              f"a spoof) on {len(faulty)} ({named}), which raised {sum(r['n_alarms'] for r in faulty)} of the alarms")
    off = [r for r in results if r.get("compass_said")]
    if off:
        sure = sum(1 for r in off if "before its first alarm" in r["compass_said"])
        print(f"guard replay says the compass read {SAY_DEG:g} degrees or more off by heading on {len(off)} of them "
              f"({sure} before its first alarm), which raised {sum(r['alarms'].get('mag', 0) for r in off)} of the "
              f"{total.get('mag', 0)} magnetometer alarms")
    live = [r["compass_said_live"] for r in results if r.get("compass_said_live")]
    if live or off:
        at_alarm = sum(1 for x in live if x["at_first_alarm"])
        print(f"guard run would say it on {len(live)} ({at_alarm} at the magnetometer's first alarm, the others "
              f"at a minute's fit)")
    since = [x for r in results for x in r.get("new_after_motors_s", [])]
    if since:
        near = [x for x in since if x is not None and x < OPEN_S]
        print(f"{len(near)} of the {len(since)} new alarms came within {OPEN_S:g} s of a motors' start heard in the "
              f"IMU ({sum(1 for x in near if x < 10.0)} within 10 s), {sum(1 for x in since if x is None)} before "
              "any was heard")
    for key, what in (("wander_said_live", "its accelerometers wander"),
                      ("position_said_live", "its receiver's position wanders past the model")):
        if line := said_live(results, key, what):
            print(line)
    if args.autopilot:
        print(f"the autopilot's own EKF saw {saw[0]} of the {saw[1]} GNSS velocity alarms it could be asked about "
              f"too (DataFlash and ULog logs: one of its {SAW_TOP} largest windows of the flight so far, the same "
              "way; tools/autopilot_view.py)")
    if args.attack:
        print("\n".join(attack_lines(results, args.attack)))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
