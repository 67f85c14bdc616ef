"""A ULog whose framing corrupt bytes broke loses only the messages the damage touched
(guard.sources.ulog.framing): on the real PX4 log and the simulator's paper run written as ULog,
one corrupt size or type byte, or a hole of random bytes, at several places each."""

from __future__ import annotations

import dataclasses
import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from pyulog import ULog

from guard.model.samples import GnssFix, ImuSample
from guard.sources import open_log
from guard.sources.ulog.framing import walk
from guard.sources.ulog.load import GPS_TOPICS
from guard_sim import scenario
from guard_sim.run import run

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "px4_vtol_cubeorange_short.ulg"
GNSS = set(GPS_TOPICS)
SEEDS = range(4)


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """The paper run (40 s) as ULog, and the real PX4 log where it is here."""
    d = tmp_path_factory.mktemp("framing")
    sc = dataclasses.replace(scenario.load("paper"), duration_s=40.0)
    run(sc, 1, tlog=str(d / "paper.tlog"), ulg=str(d / "paper.ulg"))
    out = {"sim": d / "paper.ulg"}
    if REAL.is_file():
        out["real"] = REAL
    return out


def messages(data: bytes) -> tuple[list[tuple[int, int, str | None]], dict[str, int]]:
    """The clean file's messages as (offset, size, topic of a data message), and each topic's id."""
    out, ids, names, pos = [], {}, {}, 16
    while pos + 3 <= len(data):
        size, kind = struct.unpack_from("<HB", data, pos)
        if kind == ord("A"):
            msg_id = struct.unpack_from("<H", data, pos + 4)[0]
            names[msg_id] = data[pos + 6:pos + 3 + size].decode()
            ids.setdefault(names[msg_id], msg_id)
        topic = names.get(struct.unpack_from("<H", data, pos + 3)[0]) if kind == ord("D") else None
        out.append((pos, size, topic))
        pos += 3 + size
    return out, ids


def count(path: Path) -> tuple[int, int, dict]:
    """GNSS fixes and IMU samples guard reads from `path`, and what it skipped."""
    with open_log(str(path)) as reader:
        samples = list(reader.samples())
        return (sum(isinstance(s, GnssFix) for s in samples), sum(isinstance(s, ImuSample) for s in samples),
                dict(reader.skipped))


def pyulog_fixes(path: Path) -> int:
    """The GNSS fixes pyulog reads from `path` by itself."""
    ulog = ULog(str(path), message_name_filter_list=list(GNSS))
    return sum(len(d.data["timestamp"]) for d in ulog.data_list if d.name in GNSS and d.multi_id == 0)


def test_clean_logs_frame_whole(logs):
    for origin, path in logs.items():
        data = path.read_bytes()
        w = walk(data)
        assert w.spans == [] and not w.appended, origin
        assert w.messages == len(messages(data)[0]), origin


def damaged(data: bytes, seed: int, how: str) -> tuple[bytes, tuple[int, int]]:
    """`data` with one GNSS data message's size or type byte corrupted, or a hole of random bytes
    over a few messages, in the middle half of the file (or, `first`, the size of the topic's first
    data message); and the span of bytes damaged."""
    rng = random.Random(seed)
    msgs, _ = messages(data)
    if how == "first":
        pos, size, _ = next(m for m in msgs if m[2] in GNSS)
        how = "size"
    else:
        pos, size, _ = rng.choice([m for m in msgs[len(msgs) // 4:3 * len(msgs) // 4] if m[2] in GNSS])
    out = bytearray(data)
    if how == "size":
        struct.pack_into("<H", out, pos, size + rng.choice([-7, 1, 13, 200, 3000]))
        return bytes(out), (pos, pos + 3 + size)
    if how == "type":
        out[pos + 2] = rng.choice([0, 0x7F, 0xFF, ord("x")])
        return bytes(out), (pos, pos + 3 + size)
    n = rng.randrange(200, 600)
    out[pos:pos + n] = bytes(rng.randrange(256) for _ in range(n))
    return bytes(out), (pos, pos + n)


@pytest.mark.parametrize("how", ["size", "first", "type", "hole"])
def test_a_broken_chain_loses_only_what_the_damage_touched(logs, tmp_path, how):
    hurt_pyulog = 0
    for origin, path in logs.items():
        data = path.read_bytes()
        clean_fixes, clean_imu, _ = count(path)
        msgs, _ = messages(data)
        for seed in SEEDS:
            bad, (a, b) = damaged(data, seed, how)
            copy = tmp_path / f"{origin}-{how}-{seed}.ulg"
            copy.write_bytes(bad)
            touched = [m for m in msgs if m[0] < b and m[0] + 3 + m[1] > a]
            fixes, imu, skipped = count(copy)
            lost_fixes = sum(m[2] in GNSS for m in touched)        # the damaged messages, no more
            lost_imu = sum(m[2] == "sensor_combined" for m in touched)
            assert clean_fixes - lost_fixes <= fixes <= clean_fixes, (origin, seed)
            assert clean_imu - lost_imu <= imu <= clean_imu, (origin, seed)
            assert skipped.get("garbage_bytes", 0) >= 3, (origin, seed, skipped)
            hurt_pyulog += pyulog_fixes(copy) < clean_fixes - lost_fixes
    if how in ("size", "first"):
        # the damage matters: read by pyulog alone, most of these copies lose fixes beyond it
        assert hurt_pyulog >= len(logs) * len(SEEDS) // 2


def test_the_skip_is_said(logs, tmp_path):
    data = logs["sim"].read_bytes()
    bad, (a, _) = damaged(data, 0, "size")
    copy = tmp_path / "said.ulg"
    copy.write_bytes(bad)
    with open_log(str(copy)) as reader:
        list(reader.samples())
        said = [n for n in reader.notes if "could not be framed" in n]
    assert len(said) == 1 and f"the first at byte {a})" in said[0]


def test_a_file_with_data_appended_is_not_walked(logs):
    data = bytearray(logs["sim"].read_bytes())
    if data[18] != ord("B"):
        pytest.skip("the simulator's ULog starts without flag bits")
    data[16 + 3 + 8] |= 1
    w = walk(bytes(data))
    assert w.appended and w.spans == [] and w.messages == 0


def test_a_byte_flipped_inside_a_format_leaves_pyulog_the_rest_of_it(logs, tmp_path):
    """A format ('F') whose text has one byte flipped in a field's name guard does not read is still
    framed: pyulog reads the topic's other fields, and every fix is read."""
    data = logs["sim"].read_bytes()
    msgs, _ = messages(data)
    gps_format = next(m for m in msgs if data[m[0] + 2] == ord("F")
                      and data[m[0] + 3:m[0] + 3 + m[1]].split(b":")[0].decode() in GNSS)
    at = data.index(b"device_id", gps_format[0], gps_format[0] + 3 + gps_format[1]) + 4
    copy = tmp_path / "garbled-format.ulg"
    copy.write_bytes(data[:at] + b"\xff" + data[at + 1:])
    assert walk(copy.read_bytes()).spans == []
    clean_fixes, clean_imu, _ = count(logs["sim"])
    fixes, imu, skipped = count(copy)
    assert (fixes, imu) == (clean_fixes, clean_imu) and "garbage_bytes" not in skipped, skipped


def test_a_corrupt_name_costs_that_topic_alone(logs, tmp_path):
    """A byte flipped in the name of the topic an 'A' adds: pyulog cannot find its format and loses
    that topic, as it would alone; every other topic reads whole (its data messages framed, not
    taken for a broken chain)."""
    data = logs["sim"].read_bytes()
    msgs, _ = messages(data)
    clean_fixes, clean_imu, _ = count(logs["sim"])
    for topic, kept in (("sensor_combined", 0), (None, 1)):
        add = next(m for m in msgs if data[m[0] + 2] == ord("A") and (
            data[m[0] + 6:m[0] + 3 + m[1]].decode() == topic if topic else data[m[0] + 6:m[0] + 3 + m[1]].decode() in GNSS))
        bad = bytearray(data)
        bad[add[0] + 7] = 0x01
        copy = tmp_path / f"name-{kept}.ulg"
        copy.write_bytes(bytes(bad))
        fixes, imu, skipped = count(copy)
        assert "garbage_bytes" not in skipped, skipped
        assert (fixes, imu)[kept] == (clean_fixes, clean_imu)[kept] and (fixes, imu)[1 - kept] == 0, (topic, fixes, imu)


def test_a_log_message_with_no_text_is_a_message(logs, tmp_path):
    """A logged message ('L') of no text is 9 bytes (a level and a time stamp), and valid."""
    data = logs["sim"].read_bytes()
    msgs, _ = messages(data)
    at = next(m for m in msgs if m[2] is not None)[0]          # before the first data message
    empty = struct.pack("<HB", 9, ord("L")) + b"6" + struct.pack("<Q", 1_000_000)
    copy = tmp_path / "empty-text.ulg"
    copy.write_bytes(data[:at] + empty + data[at:])
    assert walk(copy.read_bytes()).spans == []
    assert count(copy)[:2] == count(logs["sim"])[:2]


def test_an_id_taken_by_a_corrupt_add_leaves_the_topic_its_own(logs, tmp_path):
    """A corrupt 'A' that names the id of the IMU's or the GNSS's topic, before that topic's own 'A'
    (pyulog takes the later one): the topic's data messages, of its own size, are still framed, and
    every sample read, as pyulog alone reads them."""
    for origin, path in logs.items():
        data = path.read_bytes()
        msgs, ids = messages(data)
        clean = count(path)[:2]
        adds = [m for m in msgs if data[m[0] + 2] == ord("A")]
        for topic in ("sensor_combined", *sorted(GNSS & set(ids))):
            own = next(m for m in adds if data[m[0] + 6:m[0] + 3 + m[1]].decode() == topic)
            before = [m for m in adds if m[0] < own[0]]
            if not before:
                continue
            bad = bytearray(data)
            struct.pack_into("<H", bad, before[-1][0] + 4, ids[topic])
            copy = tmp_path / f"{origin}-{topic}-taken.ulg"
            copy.write_bytes(bytes(bad))
            assert count(copy)[:2] == clean, (origin, topic)


def test_a_log_cut_in_its_definitions_with_a_short_format_ends(logs, tmp_path):
    """A log cut inside its definitions, one format's size short: the definitions' own read stops (as
    the whole read does) and the replay ends with a line saying there is no fix, not a hang."""
    data = logs.get("real", logs["sim"]).read_bytes()
    formats = [m for m in messages(data)[0] if data[m[0] + 2] == ord("F")]
    pos, size, _ = formats[len(formats) * 3 // 4]
    cut = bytearray(data[:formats[-1][0]])
    struct.pack_into("<H", cut, pos, size - 20)
    copy = tmp_path / "cut-definitions.ulg"
    copy.write_bytes(bytes(cut))
    p = subprocess.run([sys.executable, "-m", "guard", "replay", str(copy)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 1 and "Traceback" not in p.stderr, p.stderr
    assert p.stderr.strip().splitlines()[-1].startswith(f"guard: error: {copy}: no GNSS sample"), p.stderr
