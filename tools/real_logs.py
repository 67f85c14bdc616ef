"""Every log in some folders replayed through guard: a line per log (its format, length, alarms by
sensor, the largest statistic/threshold per sensor, what guard warned), then the totals. For logs
of flights with no attack, every alarm is a false one or a fault in the vehicle: this is how guard is
measured on real vehicles it was never tuned on.

    python tools/real_logs.py ../shared/data/real LOGS_DIR ...          # the defaults
    python tools/real_logs.py LOGS_DIR --set monitor.max_wander_factor=1   # a config key changed
    python tools/real_logs.py LOGS_DIR --config my-vehicle.toml --json out/real.json

A log is .tlog, .bin or .ulg, recognised by its content; a file that is none of them is listed with
the reason and skipped.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import tomllib                                       # noqa: E402

from guard.config import parse, read                 # noqa: E402
from guard.errors import GuardError                  # noqa: E402
from guard.runtime.replay import replay              # noqa: E402

SUFFIXES = {".tlog", ".bin", ".ulg"}


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


def one(job: tuple[str, str | None, tuple[str, ...]]) -> dict:
    path, config, sets = job
    try:
        cfg = config_of(config, sets)
        r = replay(path, cfg)
    except GuardError as e:
        return {"log": path, "error": str(e)}
    alarms = Counter(str(a["sensor"]) for a in r["alarms"])
    return {"log": path, "format": r["format"], "duration_s": r["duration_s"], "alarms": dict(alarms),
            "n_alarms": sum(alarms.values()), "peak_ratio": r["peak_ratio"], "estimate_to_fix_m": r["estimate_to_fix_m"],
            "warnings": [n["text"] for n in r["notices"] if n["level"] == "warning"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", help="folders of logs (or single logs)")
    ap.add_argument("--config", help="TOML config file")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="a config key changed")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", help="write every log's result here")
    args = ap.parse_args(argv)
    logs: list[str] = []
    for f in map(Path, args.folders):
        if f.is_dir():
            logs += sorted(str(p) for p in f.iterdir() if p.suffix.lower() in SUFFIXES)
        elif f.exists():
            logs.append(str(f))
        else:
            print(f"guard: {f}: no such file or folder", file=sys.stderr)
            return 2
    try:                                            # a bad key or file, said before any log runs
        config_of(args.config, tuple(args.set))
    except GuardError as e:
        print(f"guard: {e}", file=sys.stderr)
        return 2
    jobs = [(p, args.config, tuple(args.set)) for p in logs]
    results, total, hours, fixes, far_fixes = [], Counter(), 0.0, 0, 0.0
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
            print(f"{name}: {r['format']}, {r['duration_s']:.0f} s; alarms {r['n_alarms']} ({by}); peaks {peaks}; "
                  f"estimate from the fixes {gap['max']:.1f} m at most, over 5 m at {100 * far:.1f} %")
    n = sum(1 for r in results if "error" not in r)
    quiet = sum(1 for r in results if r.get("n_alarms") == 0)
    by = ", ".join(f"{s} {k}" for s, k in sorted(total.items())) or "none"
    print(f"{n} logs, {hours:.2f} h: {sum(total.values())} alarms ({by}); {quiet} logs without one; "
          f"the estimate over 5 m from the fix at {100 * far_fixes / max(fixes, 1):.1f} % of {fixes} fixes")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
