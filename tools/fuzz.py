"""Fuzz guard's decoders and core: one bad frame must never stop the monitor.

    python tools/fuzz.py                                  # 10^6 cases over every target (hours on one core)
    python tools/fuzz.py --target tlog --cases 100000     # one target
    python tools/fuzz.py --target all --cases 60000 --engine random --seed 3
    python tools/fuzz.py --target can --replay out/fuzz-crashes/can-0123abcd.input   # a finding again
    python tools/fuzz.py --make-corpus                    # write the seed corpus (tools/fuzz-corpus/)

Targets (tools/fuzzing/targets.py): `mavlink` (the live link's receive paths: guard.sources.framing
and pymavlink's parse_buffer, then to_sample), `tlog`, `dataflash`, `ulog` (files through
guard.sources.open_log), `can` (frames through CanSource's decoding), `core` (samples through
Monitor.step); `all` splits --cases evenly between them. A case fails when anything but the target's
documented errors (guard's SourceError for a log) comes out, or an output breaks its promise
(tools/fuzzing/contract.py: a sample not finite or out of range, an estimate not finite). Each
failing input is written to --out as TARGET-SHA.input, its traceback beside it as TARGET-SHA.txt; a
hang or a crash of the interpreter is left there by libFuzzer (TARGET-timeout-...,
TARGET-crash-...). The last line sums up: cases, failing cases (and distinct failures, by exception
and place), time.

Engines: `atheris` (coverage-guided, libFuzzer; not a dependency of guard: `pip install atheris`,
a binary wheel for CPython 3.11 on x86-64 Linux) grows a corpus in --work from the seeds in --corpus;
`random` mutates the seeds blindly (bit flips, interesting values, cuts, splices), needs nothing and is
reproducible from --seed. `auto` (default) takes atheris when it is installed. Each target runs in a
process of its own (libFuzzer exits when done), one after the other; run it under `nice`.
"""

from __future__ import annotations

import argparse
import atexit
import hashlib
import importlib
import json
import logging
import os
import random
import signal
import struct
import subprocess
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

NAMES = ("mavlink", "tlog", "dataflash", "ulog", "can", "core")
REACHES = {"mavlink": ["guard.sources.framing"], "tlog": ["guard.sources.tlog"],     # imported instrumented
           "dataflash": ["guard.sources.dataflash"], "ulog": ["guard.sources.ulog"],
           "can": ["guard.sources.can", "dronecan"], "core": ["guard.core.monitor"]}
INTERESTING = [struct.pack(f, v) for f, v in (("<f", float("nan")), ("<f", float("inf")), ("<f", -3.4e38),
               ("<d", float("nan")), ("<d", -1e308), ("<i", -2**31), ("<i", 2**31 - 1), ("<H", 65535),
               ("<Q", 2**64 - 1), ("<q", -1), (">Q", 1_767_225_600_000_000))]


def have_atheris() -> bool:
    try:
        import atheris  # noqa: F401
    except ImportError:
        return False
    return True


# -- one target, in its own process -------------------------------------------------------------------

class Findings:
    """Failing cases of one target: each input written once, with its traceback; counted by signature.
    The count of cases run is written after every case (libFuzzer ends the process without Python's
    exit handlers), the rest after every finding and every 1000 cases."""

    def __init__(self, target: str, out: Path, stats: Path):
        from tools.fuzzing.targets import run
        self.target, self.out, self.stats_path, self._run = target, out, stats, run
        self.cases = self.failing = 0
        self.signatures: dict[str, int] = {}
        self.start = time.monotonic()
        out.mkdir(parents=True, exist_ok=True)
        self._count = os.open(stats.with_suffix(".count"), os.O_WRONLY | os.O_CREAT | os.O_TRUNC)

    def run(self, data: bytes) -> None:
        self.cases += 1
        try:
            self._run(self.target, data)
        except Exception as e:      # noqa: BLE001 - anything a target lets out is a finding
            self.found(data, e)
        os.pwrite(self._count, b"%20d" % self.cases, 0)
        if self.cases % 1000 == 0:
            self.save()

    def found(self, data: bytes, e: BaseException) -> None:
        self.failing += 1
        from tools.fuzzing.contract import Broken
        where = traceback.extract_tb(e.__traceback__)[-1]
        signature = (f"Broken: {str(e).split(':')[0]}" if isinstance(e, Broken)      # which promise
                     else f"{type(e).__name__} at {Path(where.filename).name}:{where.lineno}")
        first = signature not in self.signatures
        self.signatures[signature] = self.signatures.get(signature, 0) + 1
        name = f"{self.target}-{hashlib.sha1(data).hexdigest()[:16]}"
        if first or self.signatures[signature] <= 3:
            (self.out / f"{name}.input").write_bytes(data)
            text = "".join(traceback.format_exception(e))
            (self.out / f"{name}.txt").write_text(f"target {self.target}: {signature}\n\n{text}")
        if first:
            print(f"fuzz {self.target}: NEW {signature}: {str(e)[:200]} -> {self.out / name}.input",
                  file=sys.stderr, flush=True)
        self.save()

    def save(self) -> None:
        self.stats_path.write_text(json.dumps({"cases": self.cases, "failing": self.failing,
                                               "signatures": self.signatures,
                                               "seconds": round(time.monotonic() - self.start, 1)}))


def seeds_of(corpus: Path, target: str) -> list[bytes]:
    folder = corpus / target
    files = sorted(folder.iterdir()) if folder.is_dir() else []
    if files:
        return [f.read_bytes() for f in files]
    from tools.fuzzing.seeds import corpus as built
    return list(built()[target].values())


def instrument(target: str) -> None:
    """Import what the target reaches with atheris's coverage instrumentation: before anything else
    imports it (a module imported earlier is not instrumented)."""
    import atheris
    with atheris.instrument_imports(include=["guard", "pymavlink", "pyulog", "dronecan", "tools.fuzzing"]):
        for module in ("tools.fuzzing.targets", *REACHES[target]):
            importlib.import_module(module)


def worker_atheris(args, findings: Findings) -> None:
    import atheris
    work = Path(args.work) / args.worker
    work.mkdir(parents=True, exist_ok=True)
    seeds = Path(args.corpus) / args.worker
    flags = [f"-runs={args.cases}", f"-seed={args.seed}", f"-max_len={args.max_len}", f"-timeout={args.timeout}",
             f"-artifact_prefix={Path(args.out) / args.worker}-", "-rss_limit_mb=2048", "-print_final_stats=1"]
    atheris.Setup([sys.argv[0], *flags, str(work), *([str(seeds)] if seeds.is_dir() else [])], findings.run)
    atheris.Fuzz()


class Hang(Exception):
    """A case ran past --timeout."""


def mutate(rng: random.Random, data: bytes, pool: list[bytes]) -> bytes:
    """A few random edits of `data`: bit flips, interesting bytes and values, inserts, deletes, a cut,
    a splice with another seed."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 6)):
        if not b:
            b = bytearray(rng.randbytes(rng.randint(1, 64)))
            continue
        i, op = rng.randrange(len(b)), rng.randrange(8)
        if op == 0:
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1:
            b[i] = rng.choice((0, 1, 0x7F, 0x80, 0xFF, 0xFD, 0xFE, 0xA3, 0x95, 0x80))
        elif op == 2:
            n = rng.randint(1, 8)
            b[i:i + n] = rng.randbytes(n)
        elif op == 3:
            b[i:i] = rng.randbytes(rng.randint(1, 16))
        elif op == 4:
            del b[i:i + rng.randint(1, 16)]
        elif op == 5:
            del b[i:]
        elif op == 6:
            other = rng.choice(pool)
            j = rng.randrange(len(other))
            b[i:] = other[j:j + rng.randint(1, 512)]
        else:
            v = rng.choice(INTERESTING)
            b[i:i + len(v)] = v
    return bytes(b)


def worker_random(args, findings: Findings) -> None:
    pool = seeds_of(Path(args.corpus), args.worker)
    rng = random.Random(f"{args.seed}-{args.worker}")

    def hang(*_):
        raise Hang(f"a case ran past {args.timeout} s")
    signal.signal(signal.SIGALRM, hang)
    for k in range(args.cases):
        data = pool[k] if k < len(pool) else mutate(rng, rng.choice(pool), pool)
        signal.alarm(args.timeout)
        try:
            findings.run(data[:args.max_len])
        except Hang as e:
            findings.found(data, e)
        finally:
            signal.alarm(0)


def worker(args) -> int:
    logging.disable(logging.CRITICAL)       # what guard logs about a damaged input would swamp the log
    if args.engine == "atheris":
        instrument(args.worker)
    out = Path(args.out)
    findings = Findings(args.worker, out, Path(args.work) / f"{args.worker}.stats.json")
    atexit.register(findings.save)
    (worker_atheris if args.engine == "atheris" else worker_random)(args, findings)
    findings.save()
    return 0


# -- the driver ------------------------------------------------------------------------------------------

def run_target(args, target: str, cases: int) -> dict:
    """Run one target's worker process (again after a hang or a crash of the interpreter) until its
    cases are done; its stats summed."""
    total = {"cases": 0, "failing": 0, "signatures": {}, "seconds": 0.0, "died": 0}
    stats = Path(args.work) / f"{target}.stats.json"
    count, log = stats.with_suffix(".count"), Path(args.work) / f"{target}.log"
    while total["cases"] < cases and total["died"] <= 3:
        stats.unlink(missing_ok=True)
        count.unlink(missing_ok=True)
        start = time.monotonic()
        cmd = [sys.executable, __file__, "--worker", target, "--cases", str(cases - total["cases"]),
               "--engine", args.engine, "--seed", str(args.seed + total["died"]), "--out", args.out,
               "--work", args.work, "--corpus", args.corpus, "--max-len", str(args.max_len),
               "--timeout", str(args.timeout)]
        with open(log, "a") as f:
            code = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode
        got = json.loads(stats.read_text()) if stats.is_file() else {"cases": 0, "failing": 0, "signatures": {}}
        if count.is_file() and count.read_bytes().strip():
            got["cases"] = int(count.read_bytes())
        total["cases"] += got["cases"]
        total["failing"] += got["failing"]
        total["seconds"] += time.monotonic() - start
        for sig, n in got["signatures"].items():
            total["signatures"][sig] = total["signatures"].get(sig, 0) + n
        if code != 0:       # libFuzzer stopped on a hang, a leak or an interpreter crash: one failing case
            total["died"] += 1
            total["failing"] += 1
            total["signatures"][f"worker exit {code} (see {log})"] = 1
        elif got["cases"] == 0:
            break
    return total


def replay(args) -> int:
    from tools.fuzzing.targets import run
    bad = 0
    for path in args.replay:
        try:
            print(f"{path}: {dict(run(args.target, Path(path).read_bytes()))}")
        except Exception:   # noqa: BLE001 - shown, not raised: the next file is tried too
            bad += 1
            print(f"{path}: FAILS\n{traceback.format_exc()}")
    return 1 if bad else 0


def parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--target", choices=(*NAMES, "all"), default="all")
    p.add_argument("--cases", type=int, default=1_000_000, help="cases in all (split between targets for all)")
    p.add_argument("--engine", choices=("auto", "atheris", "random"), default="auto")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default=str(ROOT / "out" / "fuzz-crashes"), help="where failing inputs go")
    p.add_argument("--work", default=str(ROOT / "out" / "fuzz-work"), help="atheris's corpus, logs, stats")
    p.add_argument("--corpus", default=str(ROOT / "tools" / "fuzz-corpus"), help="the seeds, TARGET/ each")
    p.add_argument("--max-len", type=int, default=8192, help="the longest input (bytes)")
    p.add_argument("--timeout", type=int, default=10, help="seconds one case may take")
    p.add_argument("--replay", nargs="+", metavar="FILE", help="run --target on these inputs and show the result")
    p.add_argument("--make-corpus", action="store_true", help="write the seed corpus into --corpus")
    p.add_argument("--worker", choices=NAMES, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse(argv)
    if args.worker:
        return worker(args)
    if args.replay:
        if args.target == "all":
            sys.exit("--replay needs one --target")
        return replay(args)
    if args.make_corpus:
        from tools.fuzzing.seeds import write_corpus
        for path in write_corpus(Path(args.corpus)):
            print(f"{path} ({path.stat().st_size} bytes)")
        return 0
    if args.engine == "auto":
        args.engine = "atheris" if have_atheris() else "random"
        if args.engine == "random":
            print("atheris is not installed (pip install atheris): mutating blindly", file=sys.stderr)
    elif args.engine == "atheris" and not have_atheris():
        sys.exit("atheris is not installed: pip install atheris (or --engine random)")
    Path(args.work).mkdir(parents=True, exist_ok=True)
    targets = NAMES if args.target == "all" else (args.target,)
    start, cases, failing, distinct = time.monotonic(), 0, 0, 0
    for k, target in enumerate(targets):
        share = args.cases // len(targets) + (k < args.cases % len(targets))
        got = run_target(args, target, share)
        cases, failing, distinct = cases + got["cases"], failing + got["failing"], distinct + len(got["signatures"])
        print(f"{target}: {got['cases']} cases, {got['failing']} failing in {got['seconds']:.0f} s"
              + "".join(f"\n    {n} x {sig}" for sig, n in got["signatures"].items()), flush=True)
    print(f"fuzz ({args.engine}, seed {args.seed}): {cases} cases, {failing} failing ({distinct} distinct), "
          f"{time.monotonic() - start:.0f} s; inputs in {args.out}")
    return 1 if failing else 0


if __name__ == "__main__":
    sys.exit(main())
