"""`guard replay LOG_OR_FOLDER...`: logs through the detector offline, and what each one showed, in words.

`analyse` runs one log with the listeners whose findings the summary gives (the compass against the
gyro, the timeline of what the core said, the accelerometers and the receiver's position against
the GNSS velocity) and returns its report and its summary's lines. One log (`replay_log`) may also
be written out (--report, --plot, --mcap). Several logs, or folders of them (`replay_logs`, an SD
card's worth), are replayed on --jobs processes, each summary printed in the order given as soon as
it and those before it are done; a log that cannot be read is one line on stderr and the rest go on,
and a closing line counts the alarms, the quiet logs and the unreadable ones (the exit status is 1
if any was).
"""

from __future__ import annotations

import os
import sys
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import nullcontext

from guard.config import Config, dump
from guard.errors import GuardError
from guard.core.aiding.rest import G, WINDOW_S
from guard.core.judge import STANDING_GAP_S
from guard.runtime.agreement import Agreement, said as wander_said
from guard.runtime.deviation import Headings, compass_fits, said as iron_said
from guard.runtime.position_wander import PositionWander, said as position_said
from guard.runtime.replay import replay, truth_beside, write_report
from guard.sinks.plot import Trace
from guard.sinks.report import ADJUSTED, SKIPPED, FixGap
from guard.sinks.timeline import Timeline


ONE_LOG_OPTIONS = ("report", "plot", "mcap")     # what writes one log's output to one place


def analyse(path: str, cfg: Config, imu: int | None = None, gnss: int | None = None, listeners=(),
            progress: bool = False) -> tuple[dict, list[str]]:
    """The log at `path` replayed with the summary's listeners (and `listeners`): its report, with
    what they measured, and its summary's lines."""
    headings = Headings(cfg=cfg.monitor)    # the compass against the gyro over the whole log
    timeline = Timeline()                   # what the core said, in order
    agreement = Agreement()                 # the levelled accelerometers against the GNSS velocity
    position = PositionWander(cfg.monitor.filter)   # the receiver's position against its own velocity
    report = replay(path, cfg, listeners=[headings, timeline, agreement, position, *listeners],
                    progress=progress, imu=imu, gnss=gnss)
    iron, before, first_s = compass_fits(headings, report)
    report["compass_deviation"] = {**iron, **({"before_first_alarm": before} if before else {})}
    report["accelerometer_wander"] = agreement.measure()
    report["position_wander"] = position.measure()
    return report, summary(path, report, timeline, iron_said(iron, before, first_s))


def replay_log(args, cfg: Config) -> int:
    """`args.file` replayed as the command line asks; its summary printed unless the report goes to stdout."""
    trace = Trace() if args.plot else None
    log = None
    if args.mcap:
        from guard.sinks.mcap import McapLog
        log = McapLog(args.mcap, metadata={"config": cfg.source_text, "config_in_effect": dump(cfg),
                                           "source": args.file})
    try:
        report, lines = analyse(args.file, cfg, args.imu, args.gnss, [s for s in (trace, log) if s],
                                progress=args.report != "-")
    finally:
        if log:
            log.close()
    if args.report:
        write_report(report, args.report)
    if args.plot:
        from guard.sinks.plot import plot
        plot(trace, report, args.plot, truth_beside(args.file))
    if args.report != "-":
        for line in lines:
            print(line)
    return 0


def unreadable_folder(path: str) -> str | None:
    """Why `path` is a folder that could not be read (`find_logs` names such folders among the logs)."""
    if not os.path.isdir(path):
        return None
    try:
        os.listdir(path)
    except OSError as e:
        return f"{path}: cannot read the folder: {e.strerror}"
    return f"{path}: a folder, not a log"


def _each(job: tuple) -> tuple[list[str] | None, str | None, int]:
    """One of several logs (a process of the pool): its summary's lines, or the error that stopped it;
    and its alarms."""
    path, cfg, imu, gnss = job
    if error := unreadable_folder(path):
        return None, error, 0
    try:
        report, lines = analyse(path, cfg, imu, gnss)
    except GuardError as e:
        return None, str(e), 0
    return lines, None, len(report["alarms"])


def replay_logs(paths: list[str], cfg: Config, imu: int | None, gnss: int | None, jobs: int) -> int:
    """Several logs, each summary printed in the order given; 1 if any could not be read. Where a
    process of the pool dies (out of memory, a bus error reading a failing card), the logs not yet
    said are replayed again each in a process of its own, so that the one that kills it is named
    and the rest go on."""
    tally = {"alarms": 0, "alarmed": 0, "failed": 0}

    def say(lines: list[str] | None, error: str | None, n: int) -> None:
        if error is not None:
            tally["failed"] += 1
            sys.stdout.flush()
            print(f"guard: error: {error}", file=sys.stderr, flush=True)
            return
        tally["alarms"] += n
        tally["alarmed"] += n > 0
        print("\n".join(lines), flush=True)

    work = [(p, cfg, imu, gnss) for p in paths]
    jobs, done = min(jobs, len(paths)), 0
    with ProcessPoolExecutor(jobs) if jobs > 1 else nullcontext() as pool:
        try:
            for result in (pool.map(_each, work) if pool else map(_each, work)):
                say(*result)
                done += 1
        except BrokenProcessPool:
            for job in work[done:]:
                say(*_alone(job))
    failed = tally["failed"]
    print(f"{len(paths)} logs: {tally['alarms']} alarm(s) in {tally['alarmed']} of them, "
          f"{len(paths) - failed - tally['alarmed']} without"
          + (f"; {failed} could not be read (said above)" if failed else ""))
    return 1 if failed else 0


def _alone(job: tuple) -> tuple[list[str] | None, str | None, int]:
    """One log replayed in a process of its own: `_each`'s answer, or that the process died."""
    with ProcessPoolExecutor(1) as one:
        try:
            return one.submit(_each, job).result()
        except BrokenProcessPool:
            return None, (f"{job[0]}: the process replaying it died (killed: out of memory, or a read error "
                          "the system could not return)"), 0


def summary(path: str, report: dict, timeline: Timeline, iron_line: str | None) -> list[str]:
    """What a replay found, in words: a first line, then one indented line per finding."""
    alarms = report["alarms"]
    first = (f"first alarm at GNSS sample {alarms[0]['gnss_index']} ({alarms[0]['sensor']} "
             f"{alarms[0]['channel']})") if alarms else "no alarm"
    out = [f"{path}: {report['duration_s']:.1f} s, {report['gnss_samples']} GNSS samples, "
           f"{len(alarms)} alarm(s), {first}"]
    standing = sum(1 for a in alarms if a["standing"])
    if standing:
        out.append(f"  {standing} of the alarms were a standing alarm going on (its sensor re-anchored on and "
                   f"alarming again within {STANDING_GAP_S:g} s)")
    gap = report["estimate_to_fix_m"]
    if gap["fixes"]:
        out.append(f"  the estimate from the fixes: {gap['mean']:.1f} m on average, {gap['max']:.1f} m at most, "
                   f"more than {FixGap.FAR_M:g} m at {100 * gap[f'share_over_{FixGap.FAR_M:g}']:.1f} % of them")
        fused, excluded = gap["fused"], gap["excluded"]
        if excluded["fixes"]:
            out.append(f"    at the {fused['fixes']} fixes fused, {fused['mean']:.1f} m on average and "
                       f"{fused['max']:.1f} m at most; at the {excluded['fixes']} whose position an alarm had "
                       f"excluded, {excluded['mean']:.1f} m and {excluded['max']:.1f} m (the estimate held by the "
                       "other sensors)")
    out += [f"  {line}" for line in timeline.said()]
    out += [f"  {note}" for note in report["notes"]]
    for line in (iron_line, wander_said(report["accelerometer_wander"]), position_said(report["position_wander"])):
        if line:
            out.append(f"  {line}")
    if rest := report["accelerometers_at_rest"]:
        latest = "" if rest["median_of"] == rest["windows"] else f"the latest {rest['median_of']} of "
        out.append(f"  the accelerometers at rest read {rest['median_mps2']:.2f} m/s^2 where gravity is {G:.2f} "
                   f"(the median of {latest}{rest['windows']} windows of {WINDOW_S:g} s, "
                   f"{rest['min_mps2']:.2f} to {rest['max_mps2']:.2f})")
    for reason, n in sorted(report["skipped"].items(), key=lambda kv: -kv[1]):
        out.append(f"  skipped {n} {SKIPPED.get(reason, reason.replace('_', ' '))}")
    for reason, n in sorted(report["adjusted"].items(), key=lambda kv: -kv[1]):
        out.append(f"  used {n} {ADJUSTED.get(reason, reason.replace('_', ' '))}")
    return out
