"""TCPROS codec: headers, frames, service framing; properties and bad input."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.ros1 import tcpros
from cryptoros.ros1.tcpros import (
    NEED_DATA,
    ConnectionClosed,
    ConnectionHeader,
    FrameKind,
    Message,
    ServiceResponse,
    TCPROSConnection,
)

SUB_HEADER = {
    "callerid": "/listener",
    "md5sum": "992ce8a1687cec8c8bd883ec73ca41d1",
    "message_definition": "string data\n",
    "tcp_nodelay": "1",
    "topic": "/chatter",
    "type": "std_msgs/String",
}


def events(conn: TCPROSConnection) -> list:
    out = []
    while True:
        ev = conn.next_event()
        if ev is NEED_DATA:
            return out
        out.append(ev)
        if isinstance(ev, ConnectionClosed):
            return out


def feed(data: bytes, *, chunk: int | None = None, **kw) -> list:
    conn = TCPROSConnection(**kw)
    out = []
    step = chunk or max(1, len(data))
    for i in range(0, len(data), step):
        conn.receive_data(data[i : i + step])
        out += events(conn)
    conn.receive_data(b"")
    out += events(conn)
    return out


def test_header_bytes_match_ros_layout() -> None:
    raw = tcpros.encode_header({"topic": "/a", "type": "x/Y"})
    assert raw == struct.pack("<I", 4 + 8 + 4 + 8) + struct.pack("<I", 8) + b"topic=/a" + struct.pack("<I", 8) + b"type=x/Y"
    assert tcpros.decode_header(raw[4:]).as_dict() == {"topic": "/a", "type": "x/Y"}


def test_value_may_contain_equals_and_newlines() -> None:
    h = ConnectionHeader.of(message_definition="int32 A=1\nstring b\n", error="a=b")
    back = tcpros.decode_header(tcpros.encode_header(h)[4:])
    assert back == h and back["error"] == "a=b"


def test_header_then_frames_whole_and_byte_by_byte() -> None:
    frames = [b"", b"\x02\x00\x00\x00hi", b"x" * 1000]
    data = tcpros.encode_header(SUB_HEADER) + b"".join(tcpros.encode_frame(f) for f in frames)
    whole = feed(data)
    assert whole[0] == ConnectionHeader.of(SUB_HEADER)
    assert [e.data for e in whole[1:-1]] == frames
    assert whole[-1] == ConnectionClosed()
    assert feed(data, chunk=1) == whole
    assert feed(data, chunk=7) == whole


def test_service_response_framing() -> None:
    conn = TCPROSConnection(frame_kind=FrameKind.SERVICE_RESPONSE)
    conn.receive_data(tcpros.encode_header({"callerid": "/srv", "md5sum": "*"}))
    conn.receive_data(conn.send(ServiceResponse(ok=True, data=b"\x01\x00\x00\x00\x05")))
    conn.receive_data(conn.send(ServiceResponse(ok=False, data=b"boom")))
    evs = events(conn)
    assert isinstance(evs[0], ConnectionHeader)
    assert evs[1] == ServiceResponse(ok=True, data=b"\x01\x00\x00\x00\x05")
    assert evs[2].ok is False and evs[2].error == "boom"
    assert conn.send(ServiceResponse(ok=True, data=b"ab")) == b"\x01\x02\x00\x00\x00ab"


def test_frame_kind_set_after_header_for_shared_port() -> None:
    conn = TCPROSConnection()
    conn.receive_data(tcpros.encode_header({"callerid": "/c", "service": "/add", "md5sum": "*"}) + b"\x03\x00\x00\x00abc")
    header = conn.next_event()
    assert tcpros.check_service_client_header(header)["service"] == "/add"
    conn.set_frame_kind(FrameKind.MESSAGE)
    assert conn.next_event() == Message(data=b"abc")


def test_fast_path_messages_batch() -> None:
    conn = TCPROSConnection(expect_header=False)
    payload = b"".join(tcpros.encode_frame(bytes([i]) * i) for i in range(50))
    conn.receive_data(payload[:-3])
    first = conn.messages()
    conn.receive_data(payload[-3:])
    rest = conn.messages()
    assert first + rest == [bytes([i]) * i for i in range(50)]
    assert conn.pending_frame_size() is None


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize("limit", [16, 1000])
def test_oversized_declared_header_refused_before_buffering(limit: int) -> None:
    conn = TCPROSConnection(max_header_size=limit)
    conn.receive_data(struct.pack("<I", limit + 1))
    with pytest.raises(RemoteProtocolError, match="exceeds the limit"):
        conn.next_event()
    with pytest.raises(RemoteProtocolError):
        conn.next_event()  # stays failed


def test_oversized_declared_frame_refused() -> None:
    conn = TCPROSConnection(max_frame_size=100, expect_header=False)
    conn.receive_data(struct.pack("<I", 101))
    with pytest.raises(RemoteProtocolError, match="frame length 101"):
        conn.next_event()
    conn = TCPROSConnection(max_frame_size=100, expect_header=False)
    conn.receive_data(struct.pack("<I", 2**32 - 1))
    with pytest.raises(RemoteProtocolError):
        conn.messages()
    conn = TCPROSConnection(max_frame_size=100, frame_kind=FrameKind.SERVICE_RESPONSE, expect_header=False)
    conn.receive_data(b"\x01" + struct.pack("<I", 101))
    with pytest.raises(RemoteProtocolError):
        conn.next_event()


def test_field_length_beyond_header() -> None:
    body = struct.pack("<I", 50) + b"topic=/a"
    with pytest.raises(RemoteProtocolError, match="exceeds the header"):
        feed(struct.pack("<I", len(body)) + body)


@pytest.mark.parametrize("field", [b"topic/chatter", b"=value", b"top\xffic=/a", b"topic=\xc3("])
def test_bad_fields(field: bytes) -> None:
    body = struct.pack("<I", len(field)) + field
    with pytest.raises(RemoteProtocolError):
        feed(struct.pack("<I", len(body)) + body)


def test_missing_equals_message() -> None:
    body = struct.pack("<I", 13) + b"topic/chatter"
    with pytest.raises(RemoteProtocolError, match="without '='"):
        tcpros.decode_header(body)


@pytest.mark.parametrize("drop", ["topic", "type", "md5sum", "callerid"])
def test_subscriber_header_without_required_field(drop: str) -> None:
    h = ConnectionHeader.of({k: v for k, v in SUB_HEADER.items() if k != drop})
    with pytest.raises(RemoteProtocolError, match=drop):
        tcpros.check_subscriber_header(h)


def test_header_checks() -> None:
    assert tcpros.check_subscriber_header(ConnectionHeader.of(SUB_HEADER))["topic"] == "/chatter"
    with pytest.raises(RemoteProtocolError, match="global"):
        tcpros.check_subscriber_header(ConnectionHeader.of({**SUB_HEADER, "topic": "chatter"}))
    with pytest.raises(RemoteProtocolError, match="refused"):
        tcpros.check_publisher_header(ConnectionHeader.of(error="md5 mismatch"))
    with pytest.raises(RemoteProtocolError):
        tcpros.check_publisher_header(ConnectionHeader.of(callerid="/x", md5sum="abc"))
    with pytest.raises(RemoteProtocolError):
        tcpros.check_service_client_header(ConnectionHeader.of(callerid="/x", md5sum="*"))
    with pytest.raises(RemoteProtocolError):
        tcpros.check_service_server_header(ConnectionHeader.of(error="no"))


def test_eof_mid_frame_and_mid_header() -> None:
    with pytest.raises(RemoteProtocolError, match="middle"):
        feed(tcpros.encode_header(SUB_HEADER) + b"\x05\x00\x00\x00ab")
    with pytest.raises(RemoteProtocolError, match="middle"):
        feed(tcpros.encode_header(SUB_HEADER)[:10])
    with pytest.raises(RemoteProtocolError):
        feed(b"")  # closed before any header


def test_bad_ok_byte() -> None:
    conn = TCPROSConnection(frame_kind=FrameKind.SERVICE_RESPONSE, expect_header=False)
    conn.receive_data(b"\x07\x00\x00\x00\x00")
    with pytest.raises(RemoteProtocolError, match="ok byte"):
        conn.next_event()


def test_local_misuse() -> None:
    with pytest.raises(LocalProtocolError):
        ConnectionHeader(fields=(("a=b", "c"),))
    with pytest.raises(LocalProtocolError):
        ServiceResponse(ok=1, data=b"")  # type: ignore[arg-type]
    conn = TCPROSConnection()
    conn.receive_data(b"")
    with pytest.raises(LocalProtocolError):
        conn.receive_data(b"x")
    with pytest.raises(LocalProtocolError):
        conn.send("nope")  # type: ignore[arg-type]


# ---------------------------------------------------------------- properties

keys = st.text(st.characters(blacklist_characters="=", blacklist_categories=("Cs",)), min_size=1, max_size=20)
values = st.text(st.characters(blacklist_categories=("Cs",)), max_size=60)
headers = st.lists(st.tuples(keys, values), max_size=8, unique_by=lambda kv: kv[0])
bodies = st.lists(st.binary(max_size=300), max_size=8)


@given(headers, bodies, st.integers(1, 50))
def test_encode_decode_identity_and_split_invariance(fields, frames, chunk) -> None:
    data = tcpros.encode_header(fields) + b"".join(tcpros.encode_frame(f) for f in frames)
    whole = feed(data)
    assert whole[0] == ConnectionHeader(fields=tuple(fields))
    assert [e.data for e in whole[1:-1]] == frames
    assert feed(data, chunk=chunk) == whole
    assert feed(data, chunk=1) == whole


@given(st.lists(st.tuples(st.booleans(), st.binary(max_size=200)), max_size=8), st.integers(1, 30))
def test_service_roundtrip_property(responses, chunk) -> None:
    conn = TCPROSConnection(frame_kind=FrameKind.SERVICE_RESPONSE, expect_header=False)
    data = b"".join(conn.send(ServiceResponse(ok=ok, data=d)) for ok, d in responses)
    got = feed(data, chunk=chunk, frame_kind=FrameKind.SERVICE_RESPONSE, expect_header=False)
    assert [(e.ok, e.data) for e in got[:-1]] == responses


@settings(max_examples=300)
@given(st.binary(max_size=400), st.sampled_from(list(FrameKind)), st.integers(1, 40))
def test_any_bytes_give_events_or_remote_protocol_error(data, kind, chunk) -> None:
    def attempt(step: int):
        try:
            return ("ok", feed(data, chunk=step, frame_kind=kind, max_header_size=256, max_frame_size=256))
        except RemoteProtocolError:
            return ("error", None)

    whole = attempt(len(data) or 1)
    assert attempt(chunk) == whole
    assert attempt(1) == whole


# ---------------------------------------------------------------- the frame walker


def _frames(*bodies: bytes) -> bytes:
    return b"".join(tcpros.encode_frame(b) for b in bodies)


def test_frame_walker_split_whole_byte_by_byte_and_with_trailing_data():
    from cryptoros.ros1.tcpros import FrameWalker

    wire = _frames(b"a", b"", b"xyz")
    walker = FrameWalker(max_size=16)
    spans, stop, pending, error = walker.split(wire + b"\x05\x00\x00\x00ab")
    assert [wire[a:b] for a, b in spans] == [b"a", b"", b"xyz"]
    assert (stop, pending, error) == (len(wire), 5, None)
    assert walker.split(wire, count=1)[0] == [(4, 5)]
    # byte by byte through walk(): every frame start is seen once
    walker = FrameWalker(max_size=16)
    started = sum(walker.walk(wire[i : i + 1])[1] for i in range(len(wire)))
    assert started == 3


def test_frame_walker_checks_the_length_before_buffering():
    from cryptoros.ros1.tcpros import FrameTooLarge, FrameWalker

    walker = FrameWalker(max_size=2)
    spans, stop, pending, error = walker.split(_frames(b"ok") + struct.pack("<I", 3))
    assert spans == [(4, 6)] and stop == 6 and pending is None
    assert isinstance(error, FrameTooLarge) and error.size == 3
    with pytest.raises(FrameTooLarge):
        FrameWalker(max_size=2).walk(struct.pack("<I", 2**31))
    with pytest.raises(RemoteProtocolError, match="ok byte"):
        FrameWalker(service_response=True).walk(struct.pack("<BI", 7, 0))
