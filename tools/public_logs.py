"""The public flight logs the README's real-flight figures were measured on, fetched from where they
are published and checked byte for byte. The logs are not copied into this project (most of their
repositories carry no licence); `tools/public_logs.tsv` names each one: the set it belongs to, its
GitHub repository, the commit it was read at, its path there, its SHA-256, and the name it is given
here. With them, anyone can replay the same files (`python tools/real_logs.py OUT/set47`).

    python tools/public_logs.py fetch OUT                  # every log of the list, into OUT/<set>/<name>
    python tools/public_logs.py fetch OUT --set held23     # one set
    python tools/public_logs.py check OUT                  # the files in OUT against the list

`fetch` clones each repository once (without checking it out; from GitHub, or from `--url`, a
template such as "file:///srv/mirrors/{repo}"), writes each file as it was at its commit, and checks
its SHA-256. A repository that cannot be cloned, a commit or path no longer in it, or a file whose
bytes differ is said, and nothing of it is written or kept; the others are fetched all the same, and
the exit status is 1 if anything was said. `check` reads what is already there: a file missing or
different is said, and the exit status is 1.

Sets: `set47`, the 47 flights of "Real flights never tuned on"; `held23`, the 23 held out from all
tuning ("12 more public logs", "A 48th flight", "Held out: 10 more public logs"); `extra`, logs
named elsewhere in the README (a real GPS spoofer's ULog, tlogs without an IMU); `erle21`, the 21
Erle flights with a GNSS fix of "Held out: 21 more Erle flights" (erlerobot/logs, besides its 14
among the 47).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

LIST = Path(__file__).resolve().parent / "public_logs.tsv"
GITHUB = "https://github.com/{repo}.git"
COLUMNS = ("set", "repo", "commit", "path", "sha256", "name")
SET = re.compile(r"[A-Za-z0-9_-]+")
REPO = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*/[A-Za-z0-9_.-]+")
HEX = re.compile(r"[0-9a-f]+")


@dataclass(frozen=True)
class Entry:
    set: str
    repo: str
    commit: str
    path: str
    sha256: str
    name: str

    def target(self, out: Path) -> Path:
        return out / self.set / self.name


class ListError(Exception):
    """The list itself is malformed: its file and line are named."""


def read_list(path: Path) -> list[Entry]:
    """The list's entries; a ListError names the file and line of one that is malformed."""
    entries = []
    with open(path, newline="") as f:
        for n, row in enumerate(csv.reader(f, delimiter="\t"), start=1):
            if not row or row[0].startswith("#"):
                continue
            if tuple(row) == COLUMNS:
                continue
            if len(row) != len(COLUMNS):
                raise ListError(f"{path}:{n}: {len(row)} columns, not {len(COLUMNS)} ({', '.join(COLUMNS)})")
            e = Entry(*(c.strip() for c in row))
            why = problem(e)
            if why:
                raise ListError(f"{path}:{n}: {why}")
            entries.append(e)
    targets = [Path(e.set) / e.name for e in entries]     # one file per target, and none a folder of another
    seen = set(targets)
    if len(seen) < len(targets) or any(p in seen for t in targets for p in t.parents):
        raise ListError(f"{path}: an entry is named twice, or inside another entry's file")
    return entries


def problem(e: Entry) -> str | None:
    """What is wrong with one entry of the list, or None."""
    parts = Path(e.name).parts
    if not SET.fullmatch(e.set):
        return f"set {e.set!r}: letters, digits, - and _ only"
    if not REPO.fullmatch(e.repo) or ".." in e.repo:
        return f"repo {e.repo!r}: owner/name"
    if len(e.commit) != 40 or not HEX.fullmatch(e.commit):
        return f"commit {e.commit!r}: 40 lower-case hex digits"
    if len(e.sha256) != 64 or not HEX.fullmatch(e.sha256):
        return f"sha256 {e.sha256!r}: 64 lower-case hex digits"
    if not e.path or e.path.startswith("-"):
        return f"path {e.path!r}: a path in the repository"
    if not parts or Path(e.name).is_absolute() or any(p in (".", "..") for p in e.name.split("/")):
        return f"name {e.name!r}: a relative path without . or .."
    return None


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fetch(entries: list[Entry], out: Path, url: str, say) -> int:
    """Each repository cloned once, each of its files written from its commit and checked; the number
    of entries that could not be had."""
    failed = 0
    by_repo: dict[str, list[Entry]] = {}
    for e in entries:
        by_repo.setdefault(e.repo, []).append(e)
    for repo, files in by_repo.items():
        todo = [e for e in files if not (e.target(out).is_file() and sha256(e.target(out).read_bytes()) == e.sha256)]
        if not todo:
            say(f"{repo}: {len(files)} file(s) already here")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            source = url.format(repo=repo)
            args = ["git", "clone", "--quiet", "--no-checkout"]
            if source.startswith(("https://", "http://")):
                args.append("--filter=blob:none")       # the files asked for only, not every blob of the history
            try:
                p = subprocess.run(args + ["--", source, tmp], capture_output=True, text=True)
            except OSError as err:          # no git here
                say(f"{repo}: git could not be run ({err})")
                failed += len(todo)
                continue
            if p.returncode != 0:
                why = (p.stderr.strip().splitlines() or [f"git exited {p.returncode}"])[-1]
                say(f"{repo}: could not be cloned from {source}: {why}")
                failed += len(todo)
                continue
            written = 0
            for e in todo:
                got = subprocess.run(["git", "-C", tmp, "show", "--end-of-options", f"{e.commit}:{e.path}"],
                                     capture_output=True)
                if got.returncode != 0:
                    known = subprocess.run(["git", "-C", tmp, "cat-file", "-e", f"{e.commit}^{{commit}}"],
                                           capture_output=True).returncode == 0
                    say(f"{e.set}/{e.name}: {repo} has no {e.path} at {e.commit[:12]}" if known
                        else f"{e.set}/{e.name}: {repo} has no commit {e.commit[:12]}")
                    failed += 1
                elif sha256(got.stdout) != e.sha256:
                    say(f"{e.set}/{e.name}: {repo}'s {e.path} differs from the list (SHA-256 "
                        f"{sha256(got.stdout)[:12]}, not {e.sha256[:12]}): not written")
                    failed += 1
                else:
                    try:
                        place(e.target(out), got.stdout)
                        written += 1
                    except OSError as err:
                        say(f"{e.set}/{e.name}: could not be written ({err})")
                        failed += 1
            say(f"{repo}: {written} of {len(todo)} file(s) fetched" + (f", {len(files) - len(todo)} already here"
                                                                       if len(files) > len(todo) else ""))
    return failed


def place(target: Path, data: bytes) -> None:
    """The file written whole or not at all: to a temporary file beside it, then moved into place."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".part-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def check(entries: list[Entry], out: Path, say) -> int:
    """The files already in `out` against the list: the number missing or different."""
    bad = 0
    for e in entries:
        t = e.target(out)
        if not t.is_file():
            say(f"{e.set}/{e.name}: missing ({e.repo}, {e.path})")
            bad += 1
        elif sha256(t.read_bytes()) != e.sha256:
            say(f"{e.set}/{e.name}: differs from the list ({e.repo}, {e.path})")
            bad += 1
    return bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("action", choices=("fetch", "check"))
    ap.add_argument("out", help="the folder the logs go in, one folder per set")
    ap.add_argument("--list", default=str(LIST), help="the list of logs (default: tools/public_logs.tsv)")
    ap.add_argument("--set", action="append", help="only this set (set47, held23, extra, erle21); may be repeated")
    ap.add_argument("--url", default=GITHUB, help="where a repository is cloned from, {repo} its owner/name")
    args = ap.parse_args(argv)
    try:
        entries = read_list(Path(args.list))
    except (OSError, ListError) as e:
        print(f"public_logs: {e}", file=sys.stderr)
        return 2
    if args.set:
        unknown = set(args.set) - {e.set for e in entries}
        if unknown:
            print(f"public_logs: no set {', '.join(sorted(unknown))} in {args.list}", file=sys.stderr)
            return 2
        entries = [e for e in entries if e.set in args.set]
    out = Path(args.out)
    say = lambda line: print(line, flush=True)       # noqa: E731
    bad = fetch(entries, out, args.url, say) if args.action == "fetch" else check(entries, out, say)
    print(f"{len(entries) - bad} of {len(entries)} logs in {out}" + (f"; {bad} not" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
