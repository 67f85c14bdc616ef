"""MCAP sink: written by McapLog, read back by the mcap library (round trip, rotation, I/O errors, recovery)."""

import errno
import io
import json
import logging
import os
import re

import numpy as np
import pytest
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.Log_pb2 import Log
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from guard.sinks import mcap as mcaplog
from guard.errors import SourceError
from guard.model import events as ev   # not `import Tested`: pytest would try to collect it
from guard.model.events import Alarm, Cleared, Estimate, Innovation, Notice
from guard.sinks.mcap import McapLog, recover
from guard.model.samples import GnssFix

LAT0, LON0 = 47.397742, 8.545594
META = {"config": '[detector]\nkind = "cusum"\n', "version": "0.1.0"}


def t_of(i: int) -> int:
    return 1_000_000 + 100_000 * i          # 10 Hz from t = 1 s


def fix(i: int) -> GnssFix:
    return GnssFix(t_of(i), True, LAT0 + 1e-6 * i, LON0 + 2e-6 * i, 488.0, 1.0, 2.0, 0.5, 0.2)


def estimate(i: int) -> Estimate:
    P = np.arange(1, 12) * 0.1
    return Estimate(t_of(i), i, 0.15 * i, 0.11 * i, np.pi / 2, np.linspace(0, 1, 11), P, (LAT0, LON0, 488.0))


def make_tested(i: int) -> ev.Tested:
    inn = Innovation(t_of(i), "gnss_pos", ("east", "north"), np.array([0.1, -0.2]), np.diag([1.0, 2.0]), True)
    return ev.Tested(inn, i, np.array([0.5, 1.5]), np.array([10.0, np.inf]))


ALARM = Alarm(t_of(10), 10, "gnss_pos", "north", 12.5, 10.0, 9.8, "cusum")


def step(log: McapLog, i: int) -> None:
    log.on_sample(fix(i))
    events = [estimate(i), make_tested(i)]
    events += {5: [Notice(t_of(5), "warning", "GNSS lost")], 10: [ALARM],
               15: [Cleared(t_of(15), 15, "gnss_pos", "north")]}.get(i, [])
    log.on_events(events)


def read(path):
    """(messages as (topic, schema, channel, message), metadata dict, summary) from a finished file."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        msgs = [(c.topic, s, c, m) for s, c, m in reader.iter_messages()]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        return msgs, meta, reader.get_summary()


def test_round_trip(tmp_path):
    path = tmp_path / "run.mcap"
    log = McapLog(str(path), metadata=META)
    assert log.path == str(path)
    for i in range(20):
        step(log, i)
    log.close()
    log.close()                              # idempotent
    assert (log.errors, log.lost_messages, log.path) == (0, 0, None)

    msgs, meta, summary = read(path)
    assert meta == {"guard": META}
    by_topic = {}
    for topic, schema, channel, m in msgs:
        by_topic.setdefault(topic, []).append((schema, channel, m))
    assert set(by_topic) == {"/gnss/fix", "/estimate/fix", "/estimate/state", "/innovations/gnss_pos",
                             "/alarms", "/log"}
    assert summary.statistics.message_count == len(msgs) == 20 * 4 + 1 + 2 + 2
    kinds = {t: (s.name, s.encoding, c.message_encoding) for t, [(s, c, _), *_] in by_topic.items()}
    assert kinds["/gnss/fix"] == kinds["/estimate/fix"] == ("foxglove.LocationFix", "protobuf", "protobuf")
    assert kinds["/log"] == ("foxglove.Log", "protobuf", "protobuf")
    assert kinds["/alarms"] == ("guard.Alarm", "jsonschema", "json")
    assert kinds["/estimate/state"] == ("guard.EstimateState", "jsonschema", "json")

    # log time is the vehicle's clock: t_us * 1000, in every message
    for topic, schema, _, m in msgs:
        if schema.encoding == "protobuf":
            cls = LocationFix if schema.name == "foxglove.LocationFix" else Log
            assert cls.FromString(m.data).timestamp.ToNanoseconds() == m.log_time == m.publish_time
        else:
            assert json.loads(m.data)["t_us"] * 1000 == m.log_time == m.publish_time

    schema, _, m = by_topic["/gnss/fix"][3]
    gnss = LocationFix.FromString(m.data)
    assert (gnss.latitude, gnss.longitude, gnss.altitude) == (fix(3).lat_deg, fix(3).lon_deg, 488.0)
    assert list(gnss.position_covariance)[:5] == [0.25, 0, 0, 0, 0.25]
    # Foxglove decodes with the schema stored in the file, not with our classes
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(fd)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName("foxglove.LocationFix"))
    assert cls.FromString(m.data).latitude == fix(3).lat_deg

    est = LocationFix.FromString(by_topic["/estimate/fix"][0][2].data)
    assert (est.latitude, est.longitude) == pytest.approx(estimate(0).lat_lon(), abs=1e-12)
    assert list(est.position_covariance) == [0.1, 0, 0, 0, 0.2, 0, 0, 0, 0]
    assert est.position_covariance_type == LocationFix.DIAGONAL_KNOWN
    assert abs(est.heading) < 1e-12                 # ENU yaw pi/2 (north) is heading 0
    state = json.loads(by_topic["/estimate/state"][2][2].data)
    assert state["east_m"] == 0.3 and len(state["x"]) == len(state["P_diag"]) == 11

    inn = json.loads(by_topic["/innovations/gnss_pos"][0][2].data)
    assert inn == {"t_us": t_of(0), "gnss_index": 0, "sensor": "gnss_pos", "channels": ["east", "north"],
                   "r": [0.1, -0.2], "S_diag": [1.0, 2.0], "statistic": [0.5, 1.5], "threshold": [10.0, None],
                   "fused": True, "modelled": True}

    alarms = [json.loads(m.data) for _, _, m in by_topic["/alarms"]]
    assert alarms == [
        {"kind": "alarm", "t_us": t_of(10), "gnss_index": 10, "sensor": "gnss_pos", "channel": "north",
         "statistic": 12.5, "threshold": 10.0, "offset": 9.8, "detector": "cusum", "standing": False},
        {"kind": "cleared", "t_us": t_of(15), "gnss_index": 15, "sensor": "gnss_pos", "channel": "north"}]
    logs = [Log.FromString(m.data) for _, _, m in by_topic["/log"]]
    assert [x.level for x in logs] == [Log.WARNING, Log.ERROR, Log.INFO]
    assert logs[0].message == "GNSS lost"
    assert "gnss_pos/north" in logs[1].message and "9.8 m" in logs[1].message


def test_rotation_by_size(tmp_path):
    log = McapLog(str(tmp_path / "run.mcap"), rotate_mb=0.01, chunk_size=2048, metadata=META)
    for i in range(300):
        step(log, i)
    log.close()
    assert len(log.files) >= 3
    assert log.files[:3] == [str(tmp_path / n) for n in ("run.mcap", "run-1.mcap", "run-2.mcap")]
    total, last = 0, 0
    for path in log.files:
        msgs, meta, summary = read(path)
        assert meta == {"guard": META} and summary.statistics.message_count == len(msgs) > 0
        assert msgs[0][3].log_time >= last       # files follow each other in time
        last = msgs[-1][3].log_time
        total += len(msgs)
    assert total == 300 * 4 + 5


def test_rotation_by_time_in_directory(tmp_path):
    log = McapLog(str(tmp_path / "logs"), rotate_s=10.0)
    for i in range(250):                     # 25 s of vehicle time
        step(log, i)
    log.close()
    assert len(log.files) == 3
    for path in log.files:
        assert re.fullmatch(r"guard-\d{8}-\d{6}(-\d+)?\.mcap", path.rsplit("/", 1)[-1])
        msgs, _, _ = read(path)
        assert msgs[-1][3].log_time - msgs[0][3].log_time < 10e9


def test_a_directory_keeps_its_newest_files_within_keep_mb(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    old = [logs / f"guard-2026010{d}-120000.mcap" for d in range(1, 6)]     # five days, 1 MB each
    for p in old:
        p.write_bytes(b"\0" * 1_000_000)
    other = logs / "notes.txt"
    other.write_text("not guard's: never touched\n")
    log = McapLog(str(logs), rotate_s=10.0, keep_mb=2.5)
    for i in range(250):                     # 25 s of vehicle time: three files of its own
        step(log, i)
    log.close()
    assert [p.exists() for p in old] == [False, False, False, True, True], "the oldest went first"
    assert other.exists() and all(os.path.exists(p) for p in log.files), "its own new files stay"
    assert sum(p.stat().st_size for p in logs.glob("guard-*.mcap")) <= 2.5e6 + max(
        os.path.getsize(p) for p in log.files)


def test_unwritable_directory_goes_quiet_and_retries(tmp_path, caplog):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a directory")
    with caplog.at_level(logging.ERROR, logger="guard.sinks.mcap"):
        log = McapLog(str(blocker / "sub"))
        assert log.path is None and log.errors == 1
        for i in range(400):                 # 1 s to 41 s: a retry at 31 s fails too
            step(log, i)
    [error] = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]   # once, not per retry
    assert error.startswith("MCAP log lost: ") and str(blocker / "sub") in error
    assert log.errors == 2 and log.lost_messages == 400 * 4 + 5 and log.path is None

    blocker.unlink()                         # usable again: the next retry, at 61 s, opens a file
    for i in range(400, 800):
        step(log, i)
    assert log.path is not None
    log.close()
    msgs, _, _ = read(log.files[0])
    assert msgs[0][3].log_time == t_of(600) * 1000
    assert log.lost_messages == 600 * 4 + 5 and log.errors == 2


class FullDisk(io.RawIOBase):
    """A file that takes `room` bytes, then fails like a full disk."""

    def __init__(self, room: int):
        self.room, self.n = room, 0

    def writable(self):
        return True

    def seekable(self):
        return True

    def tell(self):
        return self.n

    def seek(self, offset, whence=io.SEEK_SET):
        return self.n

    def write(self, b):
        if self.n + len(b) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.n += len(b)
        return len(b)


def test_full_disk_is_counted_and_a_new_file_opens_later(tmp_path, monkeypatch, caplog):
    real_open, calls = open, []

    def fake_open(path, mode):
        calls.append(path)
        return io.BufferedWriter(FullDisk(20_000)) if len(calls) == 1 else real_open(path, mode)

    monkeypatch.setattr(mcaplog, "open", fake_open, raising=False)
    log = McapLog(str(tmp_path / "run.mcap"), chunk_size=4096)
    with caplog.at_level(logging.ERROR, logger="guard.sinks.mcap"):
        for i in range(600):
            step(log, i)                     # never raises
    log.close()
    assert log.errors == 1 and log.lost_messages > 0
    assert sum("MCAP log lost" in r.getMessage() for r in caplog.records) == 1
    assert calls == [str(tmp_path / "run.mcap"), str(tmp_path / "run-1.mcap")] == log.files
    msgs, _, _ = read(log.files[1])
    assert len(msgs) + log.lost_messages < 600 * 4 + 5     # what the full disk took before failing is not lost


def test_recover_a_cut_file(tmp_path):
    src, cut, dst = tmp_path / "full.mcap", tmp_path / "cut.mcap", tmp_path / "recovered.mcap"
    log = McapLog(str(src), chunk_size=8192, metadata=META)
    for i in range(1000):
        step(log, i)
    log.close()
    full, _, _ = read(src)
    data = src.read_bytes()
    cut.write_bytes(data[: int(0.7 * len(data))])      # SIGKILL: no summary, a chunk cut in two

    n, channels = recover(str(cut), str(dst))
    msgs, meta, summary = read(dst)
    assert 0.65 * len(full) < n == len(msgs) < 0.85 * len(full)
    assert channels == len(summary.channels) == 6
    assert summary.statistics.message_count == n and meta == {"guard": META}
    key = lambda e: (e[0], e[3].log_time, e[3].data)     # noqa: E731
    assert [key(e) for e in msgs] == [key(e) for e in full[:n]]    # a prefix, in order
    assert recover(str(src), str(tmp_path / "again.mcap"))[0] == len(full)


def test_recover_after_kill(tmp_path):
    src, dst = tmp_path / "killed.mcap", tmp_path / "recovered.mcap"
    chunk = 8192
    log = McapLog(str(src), chunk_size=chunk)
    for i in range(1000):
        step(log, i)
    # the daemon dies here: nothing more reaches the file; read what it holds now
    killed = src.read_bytes()
    log.close()
    (tmp_path / "snapshot.mcap").write_bytes(killed)
    n, _ = recover(str(tmp_path / "snapshot.mcap"), str(dst))
    lost = 1000 * 4 + 5 - n
    assert 0 <= lost <= chunk // 60          # at most the chunk being filled (messages >= 60 bytes with framing)
    assert len(read(dst)[0]) == n


def test_clock_going_back_retries_at_once(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a directory")
    log = McapLog(str(blocker / "sub"))
    step(log, 100)                           # t = 11 s: quiet, next attempt planned at 41 s
    blocker.unlink()
    step(log, 0)                             # t = 1 s: the autopilot rebooted; no wait for 41 s
    assert log.path is not None and log.errors == 1
    log.close()
    assert len(read(log.files[0])[0]) == 4


def test_recover_edge_cases(tmp_path):
    stub = tmp_path / "stub.mcap"
    stub.write_bytes(b"\x89MCAP0\r\n\x01\x00")        # killed while writing the header
    assert recover(str(stub), str(tmp_path / "out.mcap")) == (0, 0)
    assert read(tmp_path / "out.mcap")[2].statistics.message_count == 0
    (tmp_path / "notes.txt").write_text("not an mcap")
    with pytest.raises(SourceError):
        recover(str(tmp_path / "notes.txt"), str(tmp_path / "out2.mcap"))
    with pytest.raises(SourceError):
        recover(str(tmp_path / "missing.mcap"), str(tmp_path / "out3.mcap"))
