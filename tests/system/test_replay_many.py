"""`guard replay` on several logs or a folder of them, as an operator replays an SD card: each log's
summary in the order given, on one process or several alike; a log that cannot be read said in one
line while the rest go on; a closing count; the options that write one log's output refused."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import random
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from guard.cli import main
from guard.config import Config
from guard.runtime import replay_command
from guard.runtime.replay_command import replay_logs
from guard.sources import find_logs
from guard_sim import scenario
from guard_sim.run import run
from guard_sim.scenario import Attack

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "px4_vtol_cubeorange_short.ulg"


def guard(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "guard", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300)


@pytest.fixture(scope="module")
def card(tmp_path_factory) -> Path:
    """A folder as an SD card holds it: a clean drive as tlog, an attacked one as ULog in a folder of
    its own, each with the simulator's truth beside it, a .bin of random bytes, a note; and the real
    PX4 log where it is here."""
    d = tmp_path_factory.mktemp("card")
    (d / "2026-11-29").mkdir()
    clean = dataclasses.replace(scenario.load("clean"), duration_s=40.0)
    run(clean, 1, tlog=str(d / "a-clean.tlog"))
    attacked = dataclasses.replace(clean, attacks=(Attack("step", "gnss_pos", "north", 10.0, 30.0),))
    run(attacked, 2, tlog=str(d / "attacked.tlog"), ulg=str(d / "2026-11-29" / "b-attacked.ulg"))
    (d / "attacked.tlog").unlink()
    rng = random.Random(0)
    (d / "c-broken.bin").write_bytes(bytes(rng.randrange(256) for _ in range(3000)))
    (d / "notes.txt").write_text("battery 3, props changed\n")
    if REAL.is_file():
        shutil.copy(REAL, d / "2026-11-29" / REAL.name)
    return d


def firsts(stdout: str) -> list[str]:
    """Each log's first summary line, and the closing count."""
    return [line for line in stdout.splitlines() if not line.startswith(" ")]


def test_a_folder_is_each_log_in_order_the_unreadable_said_and_a_count(card, tmp_path):
    p = guard("replay", str(card), "--jobs", "2", cwd=tmp_path)
    assert p.returncode == 1 and "Traceback" not in p.stderr
    lines = firsts(p.stdout)
    names = [line.split(":")[0] for line in lines[:-1]]
    real = [str(card / "2026-11-29" / REAL.name)] if REAL.is_file() else []
    assert names == [str(card / "2026-11-29" / "b-attacked.ulg"), *real, str(card / "a-clean.tlog")]
    by_name = dict(zip(names, lines))
    assert ", first alarm at GNSS sample " in by_name[names[0]] and by_name[names[0]].endswith("(gnss_pos north)")
    assert ", 0 alarm(s), no alarm" in by_name[str(card / "a-clean.tlog")]
    assert p.stderr.strip().splitlines() == [f"guard: error: {card / 'c-broken.bin'}: not a log guard reads "
                                             "(known formats: tlog, dataflash, ulog)"]
    n = len(names) + 1
    assert lines[-1].startswith(f"{n} logs: ") and lines[-1].endswith("; 1 could not be read (said above)")
    assert "notes.txt" not in p.stdout + p.stderr and "truth.json" not in p.stdout + p.stderr


def test_one_process_or_two_say_the_same(card, tmp_path):
    logs = [str(card / "a-clean.tlog"), str(card / "2026-11-29")]
    one, two = (guard("replay", *logs, "--jobs", j, cwd=tmp_path) for j in ("1", "2"))
    assert one.returncode == two.returncode == 0, one.stderr
    assert one.stdout == two.stdout and one.stdout.rstrip().splitlines()[-1].endswith(" without")


def test_a_single_log_is_replayed_as_before(card, tmp_path):
    p = guard("replay", str(card / "a-clean.tlog"), cwd=tmp_path)
    assert p.returncode == 0 and firsts(p.stdout)[0].startswith(f"{card / 'a-clean.tlog'}: ")
    assert " logs: " not in p.stdout


def test_what_cannot_be_replayed_is_one_line_naming_it(card, tmp_path):
    (tmp_path / "empty").mkdir()
    for args, said in (((str(card), "--plot", "x.png"), "--plot: one log's output, and "),
                       ((str(card / "a-clean.tlog"), str(card / "c-broken.bin"), "--report", "r.json", "--mcap",
                         "m.mcap"), "--report, --mcap: one log's output, and 2 logs are given"),
                       ((str(tmp_path / "empty"),), f"{tmp_path / 'empty'}: no log in it"),
                       ((str(tmp_path / "absent.bin"),), f"{tmp_path / 'absent.bin'}: no such file or folder")):
        p = guard("replay", *args, cwd=tmp_path)
        assert p.returncode == 1 and p.stdout == "", args
        assert len(p.stderr.strip().splitlines()) == 1 and said in p.stderr, (args, p.stderr)
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "r.json").exists()


def test_a_folder_holding_one_log_is_that_log(card, tmp_path):
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(card / "a-clean.tlog", one)
    p = guard("replay", str(one), "--report", "r.json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads((tmp_path / "r.json").read_text())["source"] == str(one / "a-clean.tlog")
    assert " logs: " not in p.stdout


def test_a_log_named_twice_is_replayed_once(card, tmp_path):
    p = guard("replay", str(card / "a-clean.tlog"), str(card / "2026-11-29"), str(card), "--jobs", "1", cwd=tmp_path)
    names = [line.split(":")[0] for line in firsts(p.stdout)[:-1]]
    assert names[0] == str(card / "a-clean.tlog") and len(names) == len(set(names))
    assert firsts(p.stdout)[-1].startswith(f"{len(names) + 1} logs: ")     # and the unreadable .bin


def test_a_folder_that_cannot_be_read_is_said_and_the_rest_replayed(card, monkeypatch, capsys):
    """A sub-folder the user may not read (os.walk would pass over it without a word): named among the
    logs, and said as one that could not be read. (The suite may run as root, whom no permission
    stops: the refusal is the operating system's answer, put in its place.)"""
    locked = card / "locked"
    locked.mkdir(exist_ok=True)
    real_scandir, real_listdir = os.scandir, os.listdir

    def refuse(path="."):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(os, "scandir", lambda path=".": refuse(path) if Path(path) == locked else real_scandir(path))
    monkeypatch.setattr(os, "listdir", lambda path=".": refuse(path) if Path(path) == locked else real_listdir(path))
    assert main(["tune", str(card), "--out", str(card / "never.toml")]) == 1     # tune takes folders alike
    assert capsys.readouterr().err.strip() == f"guard: error: {locked}: cannot read the folder: Permission denied"
    logs = find_logs([str(card)])
    assert str(locked) in logs
    assert replay_logs([str(card / "a-clean.tlog"), str(locked)], Config(), None, None, 1) == 1
    out, err = capsys.readouterr()
    assert err.strip() == f"guard: error: {locked}: cannot read the folder: Permission denied"
    assert out.splitlines()[-1] == "2 logs: 0 alarm(s) in 0 of them, 1 without; 1 could not be read (said above)"


def test_a_replay_process_that_dies_is_said_and_the_rest_replayed(card, tmp_path, monkeypatch, capsys):
    """A process of the pool killed while it replays one log (the system's out-of-memory killer, a
    bus error reading a failing card; here a SIGKILL the log's replay sends itself): that log is named,
    and the logs after it are replayed still."""
    logs = []
    for name in ("a", "die", "c", "d"):
        logs.append(str(tmp_path / f"{name}.tlog"))
        shutil.copy(card / "a-clean.tlog", logs[-1])
    real = replay_command.analyse

    def analyse(path, *args, **kwargs):
        if Path(path).name == "die.tlog" and multiprocessing.parent_process() is not None:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(path, *args, **kwargs)

    if multiprocessing.get_start_method() != "fork":
        pytest.skip("the pool's processes are not forked here: they would not carry the dying replay")
    monkeypatch.setattr(replay_command, "analyse", analyse)    # the pool's processes are forked with it
    assert replay_logs(logs, Config(), None, None, 2) == 1
    out, err = capsys.readouterr()
    assert err.strip() == f"guard: error: {logs[1]}: the process replaying it died (killed: out of memory, or a " \
                          "read error the system could not return)"
    assert [line.split(":")[0] for line in firsts(out)[:-1]] == [logs[0], logs[2], logs[3]]
    assert firsts(out)[-1] == "4 logs: 0 alarm(s) in 0 of them, 3 without; 1 could not be read (said above)"
