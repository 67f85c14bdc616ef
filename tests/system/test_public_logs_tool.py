"""tools/public_logs.py: the public logs behind the README's real-flight figures, fetched by git from
their repositories at the listed commits and checked byte for byte. Here the "repositories" are real
git repositories made for the test and cloned over file:// (the tool's --url); the list shipped with
the project is read as the tool reads it."""

import hashlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tools import public_logs as tool      # noqa: E402


def git(*args, cwd):
    subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True)


def repo_with(root: Path, name: str, files: dict[str, bytes]) -> str:
    """A git repository at root/name holding `files` in one commit: its commit."""
    path = root / name
    path.mkdir(parents=True)
    git("init", "-q", cwd=path)
    for rel, data in files.items():
        (path / rel).parent.mkdir(parents=True, exist_ok=True)
        (path / rel).write_bytes(data)
    git("add", "-A", cwd=path)
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "logs", cwd=path)
    return subprocess.run(["git", "rev-parse", "HEAD"], cwd=path, check=True, capture_output=True,
                          text=True).stdout.strip()


def row(set_, repo, commit, path, data, name):
    return "\t".join((set_, repo, commit, path, hashlib.sha256(data).hexdigest(), name)) + "\n"


@pytest.fixture
def world(tmp_path):
    a, b, c = b"\xa3\x95flight one", b"\xfe\x01flight two", b"ULog\x01three"
    c1 = repo_with(tmp_path / "remote", "pilot/logs", {"pxf/copter/1.BIN": a, "pxf/plane/2.BIN": b})
    c2 = repo_with(tmp_path / "remote", "lab/ulogs", {"fixtures/x.ulg": c})
    listing = tmp_path / "list.tsv"
    listing.write_text("\t".join(tool.COLUMNS) + "\n"
                       + row("set47", "pilot/logs", c1, "pxf/copter/1.BIN", a, "pilot/1.BIN")
                       + row("held23", "pilot/logs", c1, "pxf/plane/2.BIN", b, "pilot/2.BIN")
                       + row("set47", "lab/ulogs", c2, "fixtures/x.ulg", c, "lab/x.ulg"))
    url = f"file://{tmp_path / 'remote'}/{{repo}}"
    return {"list": str(listing), "url": url, "out": tmp_path / "out", "data": (a, b, c), "commit": c1}


def test_fetch_writes_each_log_at_its_commit_and_check_reads_them_back(world, capsys):
    out = world["out"]
    assert tool.main(["fetch", str(out), "--list", world["list"], "--url", world["url"]]) == 0
    a, b, c = world["data"]
    assert (out / "set47/pilot/1.BIN").read_bytes() == a and (out / "held23/pilot/2.BIN").read_bytes() == b
    assert (out / "set47/lab/x.ulg").read_bytes() == c
    assert "3 of 3 logs" in capsys.readouterr().out
    assert tool.main(["check", str(out), "--list", world["list"]]) == 0
    # fetched again: nothing cloned, all there
    assert tool.main(["fetch", str(out), "--list", world["list"], "--url", world["url"], "--set", "held23"]) == 0
    assert "1 file(s) already here" in capsys.readouterr().out
    (out / "set47/lab/x.ulg").write_bytes(c[:-1])          # a truncated copy
    assert tool.main(["check", str(out), "--list", world["list"]]) == 1
    assert "set47/lab/x.ulg: differs from the list" in capsys.readouterr().out


def test_a_file_changed_upstream_or_a_repository_gone_is_said_and_the_rest_fetched(world, tmp_path, capsys):
    listing = Path(world["list"])
    lines = listing.read_text().splitlines(keepends=True)
    changed = lines[1].split("\t")
    changed[4] = "0" * 64                                   # the list's bytes are not what the repository holds
    gone = lines[3].replace("lab/ulogs", "lab/deleted")
    listing.write_text(lines[0] + "\t".join(changed) + lines[2] + gone)
    out = world["out"]
    assert tool.main(["fetch", str(out), "--list", str(listing), "--url", world["url"]]) == 1
    said = capsys.readouterr().out
    assert "set47/pilot/1.BIN: pilot/logs's pxf/copter/1.BIN differs from the list" in said
    assert "lab/deleted: could not be cloned" in said and "1 of 3 logs" in said
    assert not (out / "set47/pilot/1.BIN").exists() and (out / "held23/pilot/2.BIN").exists()


def test_a_malformed_list_or_an_unknown_set_is_named(world, tmp_path, capsys):
    bad = tmp_path / "bad.tsv"
    bad.write_text("\t".join(tool.COLUMNS) + "\nset47\tpilot/logs\tabc\n")
    assert tool.main(["check", str(tmp_path), "--list", str(bad)]) == 2
    assert f"{bad}:2: 3 columns" in capsys.readouterr().err
    assert tool.main(["check", str(tmp_path), "--list", world["list"], "--set", "nope"]) == 2
    assert "no set nope" in capsys.readouterr().err


def test_the_shipped_list_names_the_readme_s_sets():
    entries = tool.read_list(tool.LIST)
    count = {s: sum(e.set == s for e in entries) for s in ("set47", "held23", "erle21")}
    assert count == {"set47": 47, "held23": 23, "erle21": 21}
    names = [(e.set, e.name) for e in entries]
    assert len(set(names)) == len(names), "each log named once per set"


GOOD = ("set47", "pilot/logs", "a" * 40, "x.BIN", "b" * 64, "pilot/x.BIN")


@pytest.mark.parametrize("column, value, said", [
    (0, "../../escaped", "set"), (0, "/abs", "set"), (1, "../etc", "repo"),
    (2, "--output=/tmp/injected_by_a_list_x:f.b", "commit"), (2, "A" * 40, "commit"), (4, "c" * 63, "sha256"),
    (3, "--help", "path"), (5, "../x.BIN", "name"), (5, "/x.BIN", "name"), (5, ".", "name"), (5, "a/./b.BIN", "name"),
])
def test_an_entry_that_could_write_outside_the_folder_or_reach_git_as_an_option_is_refused(tmp_path, column, value, said):
    row = list(GOOD)
    row[column] = value
    listing = tmp_path / "list.tsv"
    listing.write_text("\t".join(row) + "\n")
    with pytest.raises(tool.ListError, match=f"{listing}:1: {said}"):
        tool.read_list(listing)


def test_two_entries_on_one_file_or_one_inside_another_s_are_refused(tmp_path):
    listing = tmp_path / "list.tsv"
    other = list(GOOD)
    other[5] = "pilot/x.BIN/inner.BIN"
    for rows in ([GOOD, GOOD], [GOOD, other], [other, GOOD]):
        listing.write_text("".join("\t".join(r) + "\n" for r in rows))
        with pytest.raises(tool.ListError, match="named twice|inside another"):
            tool.read_list(listing)
