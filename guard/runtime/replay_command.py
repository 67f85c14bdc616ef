"""`guard replay`: a log through the detector offline, and what it found said in words.

`replay_log` runs one log with the listeners whose findings the summary gives (the compass against
the gyro, the timeline of what the core said, the accelerometers and the receiver's position against
the GNSS velocity), writes what was asked (--report, --plot, --mcap) and prints the summary
(`summary`: its lines).
"""

from __future__ import annotations

from guard.config import Config, dump
from guard.core.aiding.rest import G, WINDOW_S
from guard.core.judge import STANDING_GAP_S
from guard.runtime.agreement import Agreement, said as wander_said
from guard.runtime.deviation import Headings, compass_fits, said as iron_said
from guard.runtime.position_wander import PositionWander, said as position_said
from guard.runtime.replay import replay, truth_beside, write_report
from guard.sinks.plot import Trace
from guard.sinks.report import ADJUSTED, SKIPPED, FixGap
from guard.sinks.timeline import Timeline


def replay_log(args, cfg: Config) -> int:
    """`args.file` replayed as the command line asks; its summary printed unless the report goes to stdout."""
    headings = Headings(cfg=cfg.monitor)    # the compass against the gyro over the whole log
    timeline = Timeline()                   # what the core said, in order
    agreement = Agreement()                 # the levelled accelerometers against the GNSS velocity
    position = PositionWander(cfg.monitor.filter)   # the receiver's position against its own velocity
    listeners = [headings, timeline, agreement, position]
    trace = Trace() if args.plot else None
    if trace:
        listeners.append(trace)
    log = None
    if args.mcap:
        from guard.sinks.mcap import McapLog
        log = McapLog(args.mcap, metadata={"config": cfg.source_text, "config_in_effect": dump(cfg),
                                           "source": args.file})
        listeners.append(log)
    try:
        report = replay(args.file, cfg, listeners=listeners, progress=args.report != "-", imu=args.imu, gnss=args.gnss)
    finally:
        if log:
            log.close()
    iron, before, first_s = compass_fits(headings, report)
    report["compass_deviation"] = {**iron, **({"before_first_alarm": before} if before else {})}
    report["accelerometer_wander"] = agreement.measure()
    report["position_wander"] = position.measure()
    if args.report:
        write_report(report, args.report)
    if args.plot:
        from guard.sinks.plot import plot
        plot(trace, report, args.plot, truth_beside(args.file))
    if args.report != "-":
        for line in summary(args.file, report, timeline, iron_said(iron, before, first_s)):
            print(line)
    return 0


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
