"""Damaged copies of real logs, replayed: what a corrupt or cut log costs, and that it never costs a traceback.

    python tools/damaged_logs.py FOLDER_OR_LOG... [--jobs 2] [--seed 0] [--json OUT.json]

Each log (.tlog, .bin, .ulg, as tools/real_logs.py finds them) is replayed whole, then as four damaged
copies written to a temporary folder, each through the `guard replay` command a user runs:
- `cut37`, `cut71`: cut at 37 and 71 % of its bytes (a download stopped, a card pulled);
- `flips`: 40 bytes set at random past its first tenth (a card's bit rot);
- `hole`: up to 5,000 bytes taken out between a quarter and half of the way (a lost block).
Per copy: the exit status, the last line of its error where it failed (it must be one line naming
the file: a traceback is a failure of this tool's check), and the GNSS samples its report read
against the whole log's. A cut copy can read at most its share of the fixes; a flipped or holed one
should lose only what the damage touched. The damage is drawn from --seed and the file's name, so a
run is repeatable. The last lines sum up per kind of damage: copies, tracebacks, errors, and the
median and least share of the whole log's GNSS samples read.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import random
import statistics
import subprocess
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from guard.errors import GuardError                  # noqa: E402
from tools.real_logs import logs_in                  # noqa: E402

KINDS = ("cut37", "cut71", "flips", "hole")
MIN_BYTES = 1024        # a file this small is not damaged, only replayed


def damaged(data: bytes, kind: str, rnd: random.Random) -> bytes:
    if kind.startswith("cut"):
        return data[:len(data) * int(kind[3:]) // 100]
    b = bytearray(data)
    if kind == "flips":
        for _ in range(40):
            b[rnd.randrange(len(b) // 10, len(b))] = rnd.randrange(256)
    else:
        at = rnd.randrange(len(b) // 4, max(len(b) // 2, len(b) // 4 + 1))
        del b[at:at + rnd.randrange(1, 5001)]
    return bytes(b)


def replayed(path: Path, report: Path) -> dict:
    """`guard replay PATH --report REPORT` as a user runs it: exit status, GNSS samples, last error line."""
    run = subprocess.run([sys.executable, "-m", "guard", "replay", str(path), "--report", str(report)],
                         capture_output=True, text=True, cwd=ROOT)
    out = {"status": run.returncode, "traceback": "Traceback" in run.stderr + run.stdout}
    if run.returncode == 0 and report.exists():
        out["gnss"] = json.loads(report.read_text())["gnss_samples"]
    else:
        lines = run.stderr.strip().splitlines()
        out["error"] = lines[-1] if lines else ""
    return out


def one(job: tuple[str, int]) -> dict:
    log, seed = job
    src = Path(log)
    with tempfile.TemporaryDirectory() as tmp:
        whole = replayed(src, Path(tmp) / "whole.json")
        result = {"log": log, "whole": whole, "copies": {}}
        data = src.read_bytes()
        if len(data) < MIN_BYTES:                   # nothing to damage: the whole log's replay says what it is
            return result
        for kind in KINDS:
            rnd = random.Random(f"{seed}:{src.name}:{kind}:{hashlib.sha256(data[:4096]).hexdigest()}")
            copy = Path(tmp) / f"{kind}{src.suffix}"
            copy.write_bytes(damaged(data, kind, rnd))
            got = replayed(copy, Path(tmp) / f"{kind}.json")
            if "error" in got:
                got["error"] = got["error"].replace(str(copy), f"<{kind} copy>")
            result["copies"][kind] = got
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("paths", nargs="+", help="logs, or folders of them")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="write every copy's result here")
    args = ap.parse_args(argv)
    try:
        logs = logs_in(args.paths)
    except GuardError as e:
        print(f"guard: {e}", file=sys.stderr)
        return 2
    with ProcessPoolExecutor(max(1, args.jobs)) as ex:
        results = list(ex.map(one, [(log, args.seed) for log in logs]))
    for r in results:
        whole = r["whole"].get("gnss")
        for kind, c in r["copies"].items():
            if c["traceback"] or "error" in c:
                print(f"{Path(r['log']).name} {kind}: status {c['status']}"
                      f"{', TRACEBACK' if c['traceback'] else ''}: {c.get('error', '')[:160]}")
            elif whole and c["gnss"] < whole and not kind.startswith("cut"):
                print(f"{Path(r['log']).name} {kind}: {c['gnss']} of {whole} GNSS samples read")
    read = [r for r in results if r["whole"].get("gnss")]
    print(f"{len(logs)} logs, {len(read)} read whole ({len(logs) - len(read)} not: "
          f"{sum(r['whole']['traceback'] for r in results)} tracebacks)")
    for kind in KINDS:
        copies = [r["copies"][kind] for r in read if kind in r["copies"]]
        shares = [r["copies"][kind]["gnss"] / r["whole"]["gnss"] for r in read
                  if "gnss" in r["copies"].get(kind, {})]
        print(f"{kind}: {len(copies)} copies, {sum(c['traceback'] for c in copies)} tracebacks, "
              f"{sum('error' in c for c in copies)} errors; GNSS samples read, of the whole log's: median "
              f"{statistics.median(shares) if shares else 0:.3f}, least {min(shares, default=0):.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    bad = sum(c["traceback"] for r in results for c in [r["whole"], *r["copies"].values()])
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
