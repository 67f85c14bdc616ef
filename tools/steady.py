"""The steady suite: `make test`'s tests (--all: both tiers) N times in a row on a fresh clone, to the first failure.

    python tools/steady.py --runs 20                 # 20 runs of make test's tier of HEAD
    python tools/steady.py --runs 1 --all            # both tiers: make test's and make test-long's
    python tools/steady.py --runs 5 -- tests/unit    # pytest arguments after -- (instead of make test's)

A flaky test blocks landings at random; this finds one before CI does. The clone is of the commit
checked out (uncommitted changes are not in it), installed once with the README's test command
(`make install-test`), then `python -m pytest` is run N times with the arguments `make test` gives it
(the Makefile's PYTEST_ARGS: every core, a test file per worker, the tests marked long left out;
with --all, without that choice: both tiers) unless others follow `--`. The
shared data folder beside the checkout, where there is one, is linked beside the clone, so that the
tests of the real logs run rather than skip. Each run's
outcome and time is printed as it ends, and the summary names the failing run's first failures;
the exit status is that of the first failing run (0 if none failed).
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def make_test_args(clone: Path) -> list[str]:
    """The pytest arguments `make test` passes (the Makefile's PYTEST_ARGS, as make expands it: it may be
    written with the Makefile's other variables)."""
    run = subprocess.run(["make", "-s", "--no-print-directory", "--eval",
                          "print-pytest-args: ; $(info $(PYTEST_ARGS))@:", "print-pytest-args"],
                         cwd=clone, capture_output=True, text=True)
    return shlex.split(run.stdout) if run.returncode == 0 else []


def without_marks(pytest_args: list[str]) -> list[str]:
    """The arguments without their `-m EXPR` (the choice of a tier): both tiers."""
    out, skip = [], False
    for a in pytest_args:
        if skip:
            skip = False
        elif a == "-m":
            skip = True
        elif not a.startswith("-m"):
            out.append(a)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=20, help="how many runs in a row (default: 20)")
    p.add_argument("--keep", action="store_true", help="keep the clone (its path is printed)")
    p.add_argument("--all", action="store_true", help="both tiers: the tests marked long too")
    p.add_argument("pytest_args", nargs="*", help="arguments for pytest, after --")
    args = p.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="guard-steady-"))
    clone = work / "guard"
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
    shared = ROOT.parent / "shared"
    if shared.is_dir():         # the real logs beside the clone too, so that the tests reading them run
        (work / "shared").symlink_to(shared)
    print(f"steady: {args.runs} runs of {head} in {clone}", flush=True)
    subprocess.run(["make", "install-test"], cwd=clone, check=True)
    python = clone / ".venv" / "bin" / "python"
    pytest_args = args.pytest_args or make_test_args(clone)
    if args.all and not args.pytest_args:
        pytest_args = without_marks(pytest_args)
    print(f"steady: python -m pytest {shlex.join(pytest_args)}", flush=True)
    times = []
    for i in range(1, args.runs + 1):
        start = time.monotonic()
        run = subprocess.run([str(python), "-m", "pytest", "-q", "-p", "no:cacheprovider", *pytest_args],
                             cwd=clone, capture_output=True, text=True)
        times.append(time.monotonic() - start)
        tail = run.stdout.strip().splitlines()[-1] if run.stdout.strip() else run.stderr.strip()[-200:]
        print(f"run {i}/{args.runs}: exit {run.returncode} in {times[-1] / 60:.1f} min: {tail}", flush=True)
        if run.returncode != 0:
            failed = [line for line in run.stdout.splitlines() if line.startswith(("FAILED", "ERROR"))]
            print("\n".join(failed[:20]) or run.stdout[-3000:], flush=True)
            print(f"steady: run {i} of {args.runs} failed; {i - 1} passed before it")
            return run.returncode
    print(f"steady: {args.runs} of {args.runs} runs passed ({min(times) / 60:.1f} to {max(times) / 60:.1f} min each)")
    if not args.keep:
        subprocess.run(["rm", "-rf", str(work)], check=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
