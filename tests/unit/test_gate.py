"""The public listener's per-stream gate, with no sockets: preamble -> token ->
admission -> reply, and the bytes behind the preamble handed on explicitly."""

from __future__ import annotations

import pytest

from cryptoros.errors import LocalProtocolError, PolicyDenied, RemoteProtocolError
from cryptoros.policy.ros1 import check_local_subscriber_header
from cryptoros.grants import Grant, Grants
from cryptoros.tokens import AccessToken
from cryptoros.tunnel import NEED_DATA, Preamble, PreambleReader, PreambleReply, encode
from interceptor.gate import REFRESH, PendingStreams, PreambleReceived, StreamGate, Target, feed_problem

def _access() -> AccessToken:
    grants = Grants([Grant(node="/listener", action="subscribe", name="/chatter", type="std_msgs/String")])
    return AccessToken(subject="alice", jti="j1", issued_at=0, expires_at=10**10, grants=grants, thumbprint="t",
                       claims={})


def _preamble(purpose: str = "topic", target: str = "7") -> bytes:
    return encode(Preamble(token="header.payload.signature", purpose=purpose, target=target))


def _gate(**purposes):
    return StreamGate(purposes or {"topic": lambda preamble: Target(("endpoint", preamble.target))})


def _admit(gate: StreamGate, **kw):
    args = {"feed": None, "allow_new_stream": lambda _subject: True, "open_streams": 0, "max_streams": 8}
    args.update(kw)
    return gate.admit(_access(), **args)


@pytest.mark.parametrize("how", ["whole", "byte by byte"])
def test_a_preamble_with_trailing_data_is_admitted_and_the_rest_handed_on(how):
    data = _preamble() + b"\x10\x00\x00\x00first header"
    gate = _gate()
    chunks = [data] if how == "whole" else [data[i:i + 1] for i in range(len(data))]
    event = NEED_DATA
    for chunk in chunks:
        gate.receive_data(chunk)
        event = gate.next_event()
        if event is not NEED_DATA:
            break
    assert isinstance(event, PreambleReceived)
    assert event.preamble.purpose == "topic"
    admitted = _admit(gate)
    assert (admitted.purpose, admitted.target, admitted.resolved) == ("topic", "7", ("endpoint", "7"))
    reply = PreambleReader(PreambleReply)
    reply.receive_data(gate.accept("our-token"))
    assert reply.next_event() == PreambleReply(ok=True, token="our-token")
    rest = b"".join(chunks)[len(_preamble()):] if how == "whole" else b""
    handed = gate.trailing_data
    if how == "whole":
        assert handed == rest
    else:  # fed byte by byte the event came at the preamble's last byte: the rest is still to come
        assert handed == b""


def test_an_incomplete_preamble_needs_data_and_garbage_is_a_remote_protocol_error():
    gate = _gate()
    gate.receive_data(_preamble()[:-1])
    assert gate.next_event() is NEED_DATA
    bad = _gate()
    with pytest.raises(RemoteProtocolError):  # refused as soon as the head is seen
        bad.receive_data(b"GET / HTTP/1.1\r\n\r\n" + b"x" * 64)
        bad.next_event()


@pytest.mark.parametrize(
    "purpose, kw, reason",
    [
        ("ros2", {}, "bad_purpose"),  # no role registered it: fail closed
        ("topic", {"feed": PolicyDenied("feed_stale", "old")}, "feed_stale"),
        ("topic", {"allow_new_stream": lambda _s: False}, "rate_limited"),
        ("topic", {"open_streams": 8}, "connection_limit"),
    ],
)
def test_each_refusal_has_its_reason_and_nothing_is_handed_on(purpose, kw, reason):
    gate = _gate()
    gate.receive_data(_preamble(purpose=purpose))
    assert isinstance(gate.next_event(), PreambleReceived)
    with pytest.raises(PolicyDenied) as info:
        _admit(gate, **kw)
    assert info.value.reason == reason
    reply = PreambleReader(PreambleReply)
    reply.receive_data(gate.refuse())
    assert reply.next_event() == PreambleReply(ok=False, error="denied")
    with pytest.raises(LocalProtocolError):
        gate.accept("token")  # a refused stream can never be accepted afterwards
    with pytest.raises(LocalProtocolError):
        gate.trailing_data


def test_a_stale_feed_is_refused_before_the_target_is_even_looked_at():
    looked = []
    gate = StreamGate({"topic": looked.append})
    gate.receive_data(_preamble())
    gate.next_event()
    with pytest.raises(PolicyDenied):
        _admit(gate, feed=PolicyDenied("feed_stale", "old"))
    assert looked == []


def test_the_role_target_check_refuses_unknown_targets():
    def check(preamble):
        raise PolicyDenied("unknown_target", f"no exported endpoint {preamble.target}")

    gate = StreamGate({"topic": check})
    gate.receive_data(_preamble())
    gate.next_event()
    with pytest.raises(PolicyDenied) as info:
        _admit(gate)
    assert info.value.reason == "unknown_target"


def test_a_judge_declared_by_the_target_check_runs_before_the_reply():
    """The target tells which grant the stream needs: judged on the peer's token before
    any reply, and handed on to be run again on each fresher token."""
    judged = []

    def judge(grants):
        judged.append(grants)
        raise PolicyDenied("not_granted", "/talker may not publish /chatter")

    gate = StreamGate({"topic": lambda preamble: Target(preamble.target, judge)})
    gate.receive_data(_preamble())
    gate.next_event()
    with pytest.raises(PolicyDenied) as info:
        _admit(gate)
    assert info.value.reason == "not_granted" and judged == [_access().grants]
    with pytest.raises(LocalProtocolError):
        gate.accept("token")  # refused: no reply but the refusal
    admitted_gate = StreamGate({"topic": lambda preamble: Target(preamble.target, lambda grants: None)})
    admitted_gate.receive_data(_preamble())
    admitted_gate.next_event()
    admitted = _admit(admitted_gate)
    assert admitted.resolved == "7" and admitted.judge is not None


def test_refresh_needs_no_role_and_no_target():
    gate = StreamGate({})
    gate.receive_data(_preamble(purpose=REFRESH, target=""))
    gate.next_event()
    assert _admit(gate).purpose == REFRESH


def test_the_gate_is_used_in_order():
    gate = _gate()
    with pytest.raises(LocalProtocolError):
        _admit(gate)  # no preamble yet
    gate.receive_data(_preamble())
    gate.next_event()
    with pytest.raises(LocalProtocolError):
        gate.receive_data(b"more")  # past the preamble the bytes are the role's
    with pytest.raises(LocalProtocolError):
        gate.accept("t")  # not admitted yet


def test_feed_problem_fails_closed():
    assert feed_problem(refused=False, last_feed_at=100.0, now=110.0, max_age=30).__class__ is type(None)
    assert feed_problem(refused=False, last_feed_at=None, now=110.0, max_age=30).reason == "feed_stale"
    assert feed_problem(refused=False, last_feed_at=10.0, now=110.0, max_age=30).reason == "feed_stale"
    assert feed_problem(refused=True, last_feed_at=100.0, now=110.0, max_age=30).reason == "authz_refused"


def test_a_stale_feeds_refusal_reads_the_same_however_old_the_feed():
    """Refusals are listed by their text (``cryptoros denials``): an outage is one row
    that counts up, not a row per second of the feed's age (status shows the age)."""
    first, later = (str(feed_problem(refused=False, last_feed_at=10.0, now=now, max_age=30)) for now in (50.0, 110.0))
    assert first == later == "feed_stale: revocation feed older than max_feed_age (30 s)"


def test_pending_streams_are_capped_per_key_and_released():
    pending = PendingStreams()
    pending.enter(("source", "10.0.0.1"), 2, "source")
    pending.enter(("source", "10.0.0.1"), 2, "source")
    with pytest.raises(PolicyDenied) as info:
        pending.enter(("source", "10.0.0.1"), 2, "source")
    assert info.value.reason == "pending_limit"
    pending.enter(("source", "10.0.0.2"), 2, "source")  # another source is not held back
    for _ in range(2):
        pending.leave(("source", "10.0.0.1"))
    pending.leave(("source", "10.0.0.2"))
    assert len(pending) == 0  # nothing kept for keys with no stream: bounded


def test_a_local_subscriber_is_checked_by_the_policy_before_its_stream_leaves():
    grants = Grants([Grant(node="/listener", action="subscribe", name="/chatter", type="std_msgs/String")])
    header = {"callerid": "/listener", "topic": "/chatter", "type": "std_msgs/String", "md5sum": "x"}
    check_local_subscriber_header(header, grants=grants)
    for changed, reason in (({"callerid": "/other"}, "not_granted"), ({"topic": "/secret"}, "not_granted"),
                            ({"type": "std_msgs/Int32"}, "not_granted"), ({"type": ""}, "malformed")):
        with pytest.raises(PolicyDenied) as info:
            check_local_subscriber_header({**header, **changed}, grants=grants)
        assert info.value.reason == reason


def test_a_held_long_poll_ends_before_the_feed_counts_as_stale():
    from interceptor.gate import held_feed_wait

    assert held_feed_wait(25.0, request_timeout=5.0, max_feed_age=60.0) == 25.0  # the defaults: as asked
    assert held_feed_wait(300.0, request_timeout=5.0, max_feed_age=60.0) == 54.0  # cut to fit max_feed_age
    assert held_feed_wait(300.0, request_timeout=5.0, max_feed_age=330.0) == 300.0
    assert held_feed_wait(25.0, request_timeout=5.0, max_feed_age=3.0) == 0.0  # nothing left: plain polling
    # with the server's heartbeats (each keeps the feed fresh) the hold is as asked
    assert held_feed_wait(300.0, request_timeout=5.0, max_feed_age=60.0, heartbeat=15.0) == 300.0
    # unless they are too far apart to keep it fresh: cut as without them
    assert held_feed_wait(300.0, request_timeout=5.0, max_feed_age=60.0, heartbeat=30.0) == 54.0


async def test_feed_heartbeats_are_written_when_due_and_their_table_stays_bounded():
    """The replica's one heartbeat writer, on real loopback connections: a held stream
    gets its spaces (HTTP/1.1 chunks written straight to its transport), a removed one
    none; a stream whose client stops reading is cut, not written to without end; streams
    that come and go (a client asking and hanging up in a loop) leave at most twice as
    many heap entries as live streams; due times fall on a shared grid."""
    import asyncio
    import socket

    from authz_server.app import HEARTBEAT_CHUNK, MAX_HEARTBEAT_BACKLOG, _Heartbeats

    assert HEARTBEAT_CHUNK == b"1\r\n \r\n"
    # a 15 s heartbeat falls on whole seconds, so every stream due in one second shares a wake-up
    assert _Heartbeats._aligned(12345.678, 15.0) == 12346.0 and _Heartbeats._aligned(12346.0, 15.0) == 12346.0
    assert _Heartbeats._aligned(10.01, 0.2) == pytest.approx(10.1)  # half the interval when that is under the grid

    accepted: asyncio.Queue = asyncio.Queue()

    async def on_client(reader, writer) -> None:
        await accepted.put(writer)

    server = await asyncio.start_server(on_client, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    writers = []

    async def connection():
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        theirs = await accepted.get()
        writers.extend((writer, theirs))
        return reader, writer, theirs.transport

    counted: list[int] = []
    beats = _Heartbeats(lambda: True, counted.append)
    try:
        held, _, held_transport = await connection()
        gone, _, gone_transport = await connection()
        _, stalled_writer, stalled_transport = await connection()
        stalled_writer.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled_transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        stalled_transport.write(b"x" * (1 << 20))  # its client reads none of it
        assert stalled_transport.get_write_buffer_size() > MAX_HEARTBEAT_BACKLOG
        beats.add(held_transport, 0.2)
        beats.remove(beats.add(gone_transport, 0.2))
        beats.add(stalled_transport, 0.2)
        for _ in range(10_000):
            beats.remove(beats.add(held_transport, 300.0))
        assert len(beats._due) <= 2 * len(beats._live) + 64
        received = b""
        while received.count(HEARTBEAT_CHUNK) < 2:
            received += await asyncio.wait_for(held.read(64), 10)
        assert received == HEARTBEAT_CHUNK * (len(received) // len(HEARTBEAT_CHUNK))
        assert sum(counted) >= 2
        assert stalled_transport.is_closing() and beats.dropped == 1  # cut at its first beat
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(gone.read(1), 0.5)
        assert not gone_transport.is_closing()
    finally:
        beats.close()
        for writer in writers:
            writer.transport.abort()
        server.close()
        await server.wait_closed()
