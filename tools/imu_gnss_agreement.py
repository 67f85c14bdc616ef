"""How far a vehicle's levelled accelerometers and its GNSS velocity disagree, outside any filter.

    python tools/imu_gnss_agreement.py FLIGHT.bin [FLIGHT.ulg FLIGHT.tlog ...] [--windows 0.4 1 2 4 8]
        [--jobs 2] [--json out.json]

For each log and window length W (guard.runtime.agreement says how each figure is made): the windows
measured and left out, the rms of the disagreement e between the levelled accelerometers and the
change of the receiver's velocity (m/s^2, and as a tilt, atan(e / g)), its Allan deviation (how much
e moves from one window to the next: what guard's filter cannot follow) and the rms of the GNSS
acceleration itself (how hard the vehicle manoeuvred). `guard replay` prints the 8 s figure.

A log guard cannot read, or without windows to measure (telemetry whose IMU is too slow to
integrate), is named with the reason and skipped; a file that is not there is an error.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from guard.errors import GuardError                                      # noqa: E402
from guard.runtime.agreement import MAX_STEP_S, WINDOWS_S, Agreement     # noqa: E402
from guard.runtime.replay import replay                                  # noqa: E402


def measure(path: str, windows: tuple[float, ...] = WINDOWS_S) -> dict:
    """{"log", "rows": Agreement.measure's} or {"log", "skipped": why}."""
    agreement = Agreement()
    try:
        replay(path, listeners=[agreement])
    except GuardError as e:
        return {"log": path, "skipped": str(e)}
    rows = agreement.measure(windows)
    if rows is None:
        return {"log": path, "skipped": f"no window with fixes on both ends and the IMU integrated between them "
                                        f"without a step over {MAX_STEP_S:g} s (telemetry's IMU is too slow, or guard "
                                        "never had a heading to integrate it with)"}
    return {"log": path, "rows": rows}


def show(result: dict) -> str:
    if "skipped" in result:
        return f"{result['log']}: skipped, {result['skipped']}"
    lines = [f"{result['log']}:",
             "  window   windows  left out   rms e (m/s^2)  as tilt (deg)  Allan dev. (m/s^2)  GNSS accel rms (m/s^2)"]
    for r in result["rows"]:
        if not r["windows"]:
            lines.append(f"  {r['window_s']:5.1f} s  {0:8d}  {r['left_out']:8d}")
            continue
        adev = "-" if r["allan_mps2"] is None else f"{r['allan_mps2']:.3f}"
        lines.append(f"  {r['window_s']:5.1f} s  {r['windows']:8d}  {r['left_out']:8d}  {r['rms_mps2']:14.3f}"
                     f"  {r['tilt_deg']:13.2f}  {adev:>18s}  {r['gnss_accel_rms_mps2']:22.3f}")
    return "\n".join(lines)


def _one(job):
    return measure(*job)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", help="flight logs guard reads (tlog, DataFlash .bin, ULog)")
    ap.add_argument("--windows", type=float, nargs="+", default=list(WINDOWS_S), help="window lengths, s")
    ap.add_argument("--jobs", type=int, default=1, help="logs measured at once")
    ap.add_argument("--json", help="write the figures here too")
    args = ap.parse_args(argv)
    if any(w <= 0.0 for w in args.windows) or args.jobs < 1:
        ap.error("windows must be positive and --jobs at least 1")
    missing = [p for p in args.logs if not Path(p).is_file()]
    if missing:
        print(f"error: {missing[0]}: no such file", file=sys.stderr)
        return 2
    jobs = [(p, tuple(args.windows)) for p in args.logs]
    if args.jobs > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(args.jobs) as ex:
            results = list(ex.map(_one, jobs))
    else:
        results = [_one(j) for j in jobs]
    for r in results:
        print(show(r))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
