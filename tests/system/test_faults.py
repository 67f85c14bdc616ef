"""The fault campaigns (tools/faults.py), one case of each: a link silent past its timeout, an autopilot
reboot and a lone wild time stamp, SIGKILL then mcap-recover, a full disk. The daemon is the real one on
UDP loopback; the disk is a real tmpfs (skipped where it cannot be mounted)."""

import os
import subprocess
import tempfile
from pathlib import Path

import pytest
from toolbox import load_tool

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tool():
    return load_tool("faults")


def test_a_silent_link_is_said_and_the_attack_still_caught(tool):
    c = tool.silence_case(6.0, 10.0)
    assert c["alive"] and c["warned"] and c["back"], c
    assert not c["false_alarms"] and c["delay"] is not None and c["delay"] <= 3, c


def test_a_silence_during_the_attack_clears_nothing(tool):
    c = tool.silence_case(6.0, 50.0)
    assert c["standing"] and not c["cleared_gnss"] and c["delay"] is not None, c


def test_a_reboot_restarts_the_filter_and_the_attack_after_it_is_caught(tool):
    c = tool.reboot_case("reboot", 20.0)
    assert c["reinitialised"] and c["alive"], c
    assert not c["false_alarms"] and c["delay"] is not None and c["delay"] <= 3, c


def test_a_reboot_after_the_alarm_leaves_it_standing(tool):
    c = tool.reboot_case("reboot", 55.0)
    assert any("alarm stands" in line for line in c["reinitialised"]), c
    assert c["standing"] and not c["cleared_gnss"], c


def test_a_lone_wild_time_stamp_is_dropped_not_a_reboot(tool):
    c = tool.reboot_case("wild", 20.0)
    assert not c["reinitialised"] and c["skipped"].get("time_off_base") == 1, c
    assert c["delay"] == 0 and not c["false_alarms"], c


def test_sigkill_after_the_alarm_loses_at_most_a_chunk_and_keeps_the_alarm(tool, tmp_path):
    c = tool.kill_case(15.0, tmp_path, speedup=4.0)           # vehicle time about 60 s: after the alarm
    assert c["recover_rc"] == 0 and c["alarm_logged"], c
    chunk_fixes = tool.parse({}).log.chunk_kb * 1024 / c["raw_bytes_per_fix"]
    assert c["fixes_sent"] - c["fixes"] <= chunk_fixes + 10, c


def test_a_full_disk_loses_the_log_not_the_alarm(tool, capsys):
    probe = tempfile.mkdtemp()
    try:
        mounted = os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", probe],
                                                       capture_output=True).returncode == 0
        if mounted:
            subprocess.run(["umount", probe], capture_output=True)
    finally:
        os.rmdir(probe)
    if not mounted:
        pytest.skip("a full disk needs a tmpfs mount, which needs root (and a kernel that allows it)")
    assert tool.main(["disk"]) == 0, capsys.readouterr().out
