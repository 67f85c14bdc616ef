"""The live MAVLink link (guard.sources.link.MavlinkLink) on a hostile link: stray bytes, fragments, forged
signatures, spoofed senders, floods of rejected frames.

Real loopback sockets and real MAVLink 2 bytes packed by pymavlink; the link is driven through its public
`poll` and `send`, as the daemon drives it. A frame "comes out" when poll returns its sample.
"""

from __future__ import annotations

import logging
import select
import socket
import time
from collections import Counter

import guard.sources.mavlink  # noqa: F401  (sets MAVLINK20=1 before pymavlink is imported)
import pytest
from hypothesis import given, settings, strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from guard.config import LinkConfig
from guard.model.samples import GnssFix
from guard.sources import framing
from guard.sources.link import MavlinkLink, SkipLog

LAT, LON = 404237000, -869212000
EPOCH_2015 = 1420070400
KEY = bytes(range(1, 33))
# a MAVLink 2 header that passes every check a header alone allows (flags 0, a known message id) and
# claims a 200-byte payload: pymavlink's parser waits for it and swallows the frames that follow
PLAUSIBLE_STRAY = bytes((0xFD, 200, 0, 0, 0, 1, 1, 24, 0, 0))


# --- helpers --------------------------------------------------------------------------------------------

def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sender(key: bytes | None = None, system: int = 1) -> mavlink.MAVLink:
    """The autopilot's MAVLink packer; with `key` it signs, its clock at now like pymavlink's setup_signing."""
    mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=1)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = int((time.time() - EPOCH_2015) * 100_000)
    return mav


def gps(mav: mavlink.MAVLink, t_us: int) -> bytes:
    msg = mav.gps_raw_int_encode(t_us, 3, LAT, LON, 187000, 100, 150, 500, 0, 12, h_acc=1500, vel_acc=250)
    buf = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return buf


def open_link(tmp_path=None, require_signed: bool = False, **cfg) -> tuple[MavlinkLink, tuple[str, int]]:
    """A udpin link on a free loopback port, and its address."""
    if tmp_path is not None:
        key_file = tmp_path / "signing.key"
        key_file.write_bytes(KEY)
        cfg.update(signing_key_file=str(key_file), require_signed=require_signed)
    port = free_udp_port()
    return MavlinkLink(f"udpin:127.0.0.1:{port}", LinkConfig(**cfg)), ("127.0.0.1", port)


def udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


def collect(link: MavlinkLink, until, timeout_s: float = 3.0) -> list:
    """Samples from link.poll until until(samples) holds (or timeout_s passed)."""
    got = []
    deadline = time.monotonic() + timeout_s
    while not until(got) and time.monotonic() < deadline:
        sample = link.poll(0.02)
        if sample is not None:
            got.append(sample)
    return got


def received(sock: socket.socket, wait_s: float = 0.2) -> list[bytes]:
    """Every datagram `sock` has received, waiting up to wait_s for the first."""
    got = []
    while select.select([sock], [], [], wait_s if not got else 0.0)[0]:
        got.append(sock.recv(65535))
    return got


def heartbeat(mav) -> None:
    mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                       mavlink.MAV_STATE_ACTIVE)


# --- (a) a stray byte costs no frame -----------------------------------------------------------------------

def test_a_stray_byte_per_datagram_costs_no_valid_frame():
    link, addr = open_link()
    mav, tx = sender(), udp_socket()
    n, kinds = 200, 5
    expected, got, n_prefixed, n_truncated = [], [], 0, 0
    try:
        for i in range(n):
            frame = gps(mav, 1_000_000 + i)
            kind = i % kinds
            if kind == 0:
                datagram = b"\xfd" + frame              # a stray MAVLink 2 start byte
            elif kind == 1:
                datagram = b"\xfe" + frame              # a stray MAVLink 1 start byte
            elif kind == 2:
                datagram = PLAUSIBLE_STRAY + frame      # a header that claims the frame as its payload
            elif kind == 3:
                datagram = b"\x00\x55\xfd\x01" + frame  # junk with a start byte in it
            else:
                datagram = frame + gps(mav, 0)[:25]     # a valid frame, then a cut-off one
            n_prefixed += kind < 4
            n_truncated += kind == 4
            tx.sendto(datagram, addr)
            expected.append(1_000_000 + i)
            if i % 20 == 19:                            # keep within the socket's receive buffer
                got += collect(link, lambda _: False, 0.01)
        got += collect(link, lambda more: len(got) + len(more) >= n)
    finally:
        link.close()
        tx.close()
    assert all(isinstance(s, GnssFix) for s in got)
    assert [s.t_us for s in got] == expected, "every valid frame comes out, in order"
    assert link.skipped["bad_frame"] == n_prefixed, dict(link.skipped)
    assert link.skipped["partial_frame"] == n_truncated, dict(link.skipped)


def test_pymavlink_alone_loses_the_frame_after_a_stray_start_byte():
    """The fault the link's own framing is there for: with one parser for everything, pymavlink's robust
    parsing takes a stray 0xFD's claimed length and the valid frame after it is lost."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    frame = gps(sender(), 1)
    assert not [m for m in parser.parse_buffer(b"\xfd" + frame) or [] if m.get_type() == "GPS_RAW_INT"]
    assert [f.msg_id for f in framing.split(b"\xfd" + frame).frames] == [mavlink.MAVLINK_MSG_ID_GPS_RAW_INT]


def test_tcp_stays_a_stream_and_loses_no_frame_to_stray_bytes():
    """On TCP a frame may be split across reads: it is kept and completed, and stray headers cost nothing.

    A stray header holds back the frames after it until the length it claims has arrived (at most 280
    bytes): on a stream that cannot be told sooner. The last frames are clean, as a live link goes on."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    link = MavlinkLink(f"tcp:127.0.0.1:{server.getsockname()[1]}", LinkConfig())
    peer, _ = server.accept()
    mav = sender()
    n = 66
    stream = b"".join((PLAUSIBLE_STRAY if i % 3 == 0 and i < 60 else b"\xfd" if i % 3 == 1 else b"")
                      + gps(mav, 10 + i) for i in range(n))
    try:
        for start in range(0, len(stream), 7):          # 7-byte writes: every frame split across reads
            peer.sendall(stream[start:start + 7])
            if start % 350 == 0:
                time.sleep(0.002)
        got = collect(link, lambda got: len(got) >= n)
    finally:
        link.close()
        peer.close()
        server.close()
    assert [s.t_us for s in got] == [10 + i for i in range(n)]
    assert link.skipped["partial_frame"] == 0
    assert len(link._tail) < framing.MAX_FRAME


@settings(max_examples=300, derandomize=True, deadline=None)
@given(before=st.binary(max_size=300), after=st.binary(max_size=300))
def test_any_junk_around_a_frame_in_one_datagram_costs_it_nothing(before, after):
    frame = gps(sender(), 7)
    found = framing.split(before + frame + after)
    assert frame in [f.buf for f in found.frames]


# --- (b) no frame across datagrams -------------------------------------------------------------------------

@pytest.mark.parametrize("two_senders", [False, True], ids=["one-sender", "two-senders"])
def test_fragments_from_two_datagrams_never_join(two_senders):
    link, addr = open_link()
    mav = sender()
    first, second = udp_socket(), udp_socket()
    try:
        for cut in (1, 5, 11, 20, 30):
            frame = gps(mav, 100 + cut)
            first.sendto(frame[:cut], addr)
            (second if two_senders else first).sendto(frame[cut:], addr)
        assert collect(link, lambda got: False, 0.5) == [], "no frame made of two datagrams"
        assert link.skipped["partial_frame"] == 5, dict(link.skipped)
        first.sendto(gps(mav, 999), addr)               # the link still reads whole frames
        assert [s.t_us for s in collect(link, lambda got: len(got) >= 1)] == [999]
    finally:
        link.close()
        first.close()
        second.close()


# --- (c) signing -------------------------------------------------------------------------------------------

def forged(genuine: bytes, timestamp: int) -> bytes:
    """`genuine` with its signature block replaced: the same link id, `timestamp`, a garbage signature.
    The CRC does not cover the signature block, so the frame still passes it."""
    return genuine[:-13] + genuine[-13:-12] + timestamp.to_bytes(6, "little") + b"\x5a" * 6


def test_a_forged_frame_with_a_huge_time_stamp_drops_no_genuine_frame(tmp_path):
    link, addr = open_link(tmp_path, require_signed=True)
    mav, tx = sender(KEY), udp_socket()
    n = 50
    try:
        genuine = [gps(mav, 5_000 + i) for i in range(n)]
        assert all(f[2] & 0x01 for f in genuine), "the autopilot signs"
        tx.sendto(forged(genuine[0], 2**48 - 2), addr)
        for buf in genuine:
            tx.sendto(buf, addr)
        got = collect(link, lambda got: len(got) >= n)
        tx.sendto(genuine[-1], addr)                    # a genuine frame again: a replay
        tx.sendto(gps(sender(), 1), addr)               # unsigned
        tx.sendto(gps(sender(bytes(32)), 2), addr)      # signed with another key
        late = collect(link, lambda got: False, 0.3)
    finally:
        link.close()
        tx.close()
    assert [s.t_us for s in got] == [5_000 + i for i in range(n)], "no genuine frame dropped"
    assert late == []
    assert link.skipped["bad_signature"] == 4, dict(link.skipped)
    stamps = link.conn.mav.signing.stream_timestamps
    assert max(stamps.values()) < 2**48 - 2 and len(stamps) == 1, stamps


def test_a_forged_signature_is_dropped_even_when_unsigned_frames_are_allowed(tmp_path):
    link, addr = open_link(tmp_path, require_signed=False)
    mav, tx = sender(KEY), udp_socket()
    try:
        genuine = gps(mav, 1)
        tx.sendto(forged(genuine, 2**48 - 2), addr)
        tx.sendto(genuine, addr)
        tx.sendto(gps(sender(), 2), addr)               # unsigned: allowed
        got = collect(link, lambda got: len(got) >= 2)
    finally:
        link.close()
        tx.close()
    assert [s.t_us for s in got] == [1, 2]
    assert link.skipped["bad_signature"] == 1


# --- (d) spoofed senders -----------------------------------------------------------------------------------

def test_many_spoofed_senders_leave_bounded_state_and_replies_go_to_one_peer():
    link, addr = open_link()
    mav = sender()
    autopilot, junk_listener, spoof_listener = udp_socket(), udp_socket(), udp_socket()
    autopilot_addr = autopilot.getsockname()
    n_spoofed = 2000
    ports = set()
    try:
        autopilot.sendto(gps(mav, 1), addr)
        assert [s.t_us for s in collect(link, lambda got: len(got) >= 1)] == [1]
        junk_listener.sendto(b"\x00junk" * 10, addr)
        spoof_listener.sendto(gps(mav, 2), addr)        # a valid frame from the autopilot's id, elsewhere
        for i in range(n_spoofed):
            with udp_socket() as s:
                ports.add(s.getsockname()[1])
                s.sendto(gps(mav, 10 + i) if i % 2 else b"\xfd\x05\x00" + bytes(20), addr)
            if i % 50 == 49:                            # keep within the socket's receive buffer
                collect(link, lambda got: False, 0.01)
        autopilot.sendto(gps(mav, 3), addr)
        got = collect(link, lambda got: len(got) >= 1)
        for _ in range(3):
            link.send(heartbeat)
        link.send(lambda m: m.statustext_send(mavlink.MAV_SEVERITY_CRITICAL, b"GUARD test"))
        to_autopilot = received(autopilot)
        to_junk, to_spoof = received(junk_listener), received(spoof_listener)
    finally:
        link.close()
        for s in (autopilot, junk_listener, spoof_listener):
            s.close()
    assert len(ports) > 0.9 * n_spoofed, "distinct source addresses"
    assert [s.t_us for s in got] == [3], "the autopilot is still heard; no spoofed frame is"
    assert link.skipped["other_address"] == n_spoofed // 2 + 1, dict(link.skipped)
    assert link.skipped["bad_frame"] + link.skipped["partial_frame"] >= n_spoofed // 2
    # per-sender state: one peer, pymavlink's client set never filled, a fixed set of skip reasons
    assert link.peer == autopilot_addr
    assert link.conn.clients == set() and link.conn.clients_last_alive == {}
    assert len(link.skipped) <= 5 and len(link.skip._last) <= 5, dict(link.skipped)
    assert link.conn.mav.signing.stream_timestamps == {}
    assert len(to_autopilot) == 4 and to_junk == [] and to_spoof == [], "replies go to the peer only"


def test_no_reply_before_the_autopilot_is_heard_then_to_it_alone():
    link, addr = open_link()
    stranger, autopilot = udp_socket(), udp_socket()
    try:
        stranger.sendto(b"\x00" * 30, addr)
        stranger.sendto(gps(sender(system=7), 1), addr)     # another system: not the autopilot
        collect(link, lambda got: False, 0.1)
        link.send(heartbeat)
        assert link.skipped["send_no_peer"] == 1
        autopilot.sendto(gps(sender(), 2), addr)
        assert len(collect(link, lambda got: len(got) >= 1)) == 1
        link.send(heartbeat)
        assert len(received(autopilot)) == 1 and received(stranger) == []
    finally:
        link.close()
        stranger.close()
        autopilot.close()
    assert link.skipped["other_system"] == 1


def test_a_silent_peer_is_replaced_after_the_link_timeout():
    link, addr = open_link(link_timeout_s=0.3)
    mav = sender()
    old, new = udp_socket(), udp_socket()
    new_addr = new.getsockname()
    try:
        old.sendto(gps(mav, 1), addr)
        new.sendto(gps(mav, 2), addr)                   # the peer is alive: ignored
        got = collect(link, lambda got: False, 0.2)
        time.sleep(0.35)
        new.sendto(gps(mav, 3), addr)                   # the peer has been silent past the timeout
        got += collect(link, lambda got: len(got) >= 1)
        link.send(heartbeat)
        to_old, to_new = received(old), received(new)
    finally:
        link.close()
        old.close()
        new.close()
    assert [s.t_us for s in got] == [1, 3]
    assert link.peer == new_addr and to_old == [] and len(to_new) == 1


# --- (e) logging -------------------------------------------------------------------------------------------

def test_rejected_frames_are_counted_and_logged_sparingly(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    link, addr = open_link(tmp_path, require_signed=True)
    mav, tx = sender(KEY), udp_socket()
    n = 1000
    try:
        for i in range(n):
            tx.sendto(forged(gps(mav, i), 2**48 - 2 - i), addr)
            if i % 50 == 49:
                collect(link, lambda _: False, 0.01)
        deadline = time.monotonic() + 3
        while link.skipped["bad_signature"] < n and time.monotonic() < deadline:
            link.poll(0.02)
    finally:
        link.close()
        tx.close()
    assert link.skipped["bad_signature"] == n
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) <= 3, lines                       # the first, and the rest on close (pymavlink: none)
    assert "skipped 1 bad_signature" in lines[0] and "wrong signature" in lines[0], lines
    assert f"skipped {n - 1} bad_signature" in lines[-1], lines


def test_skip_log_writes_one_line_per_reason_per_period(caplog):
    caplog.set_level(logging.INFO, logger="guard.sources.link")
    now = [0.0]
    skipped = Counter()
    skip = SkipLog(skipped, every_s=10.0, clock=lambda: now[0])
    for second in range(25):                            # one of each per second for 25 s
        now[0] = float(second)
        skip("bad_frame")
        skip("other_address", detail="127.0.0.1:9")
    skip.flush()
    lines = [r.getMessage() for r in caplog.records]
    assert skipped == {"bad_frame": 25, "other_address": 25}
    for reason in ("bad_frame", "other_address"):
        mine = [line for line in lines if reason in line]
        assert [int(line.split()[3]) for line in mine] == [1, 10, 10, 4], mine
    assert sum(r.levelno == logging.WARNING for r in caplog.records) == 4     # other_address warns


def gcs_heartbeats(gcs, tx, addr, n: int) -> None:
    """n HEARTBEATs of a ground station (MAV_TYPE_GCS, no autopilot) sent to addr."""
    for _ in range(n):
        tx.sendto(bytes(gcs.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(gcs)),
                  addr)


def test_a_link_guard_only_sends_on_hears_its_ground_station_without_counting_it():
    """link.gcs (or the alarm link of a monitor reading CAN) is drained, not read for samples: the
    ground station's own HEARTBEATs there teach it the peer and are not 'other_system' skips."""
    link, addr = open_link()
    gcs, tx = sender(system=255), udp_socket()
    try:
        gcs_heartbeats(gcs, tx, addr, 5)
        deadline = time.monotonic() + 3.0
        drained = 0
        while drained < 5 and time.monotonic() < deadline:
            drained += link.drain()
            time.sleep(0.01)
        assert drained == 5
        assert link.peer == tx.getsockname()            # it answers the ground station
        assert "other_system" not in link.skipped, link.skipped
        tx.sendto(gps(gcs, 1_000_000), addr)            # read as a source, the same frame is counted
        assert not collect(link, lambda got: False, timeout_s=0.3)
        assert link.skipped["other_system"] == 1
    finally:
        link.close()
        tx.close()


def test_a_ground_stations_heartbeats_on_the_autopilots_link_are_not_skipped_data():
    """A router that forwards the ground station's HEARTBEATs to guard's link: they are no data and
    not counted as another system's messages (every log and link would say so); its other messages
    are, and a fix from it is remembered for the silence warning."""
    link, addr = open_link()
    gcs, tx = sender(system=255), udp_socket()
    try:
        gcs_heartbeats(gcs, tx, addr, 3)
        tx.sendto(gps(gcs, 1_000_000), addr)
        assert not collect(link, lambda got: False, timeout_s=0.3)
        assert link.skipped["other_system"] == 1, link.skipped
        assert link.other_gnss == {255: 1}
    finally:
        link.close()
        tx.close()
