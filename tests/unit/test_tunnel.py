"""The interceptor-to-interceptor preamble codec: round trips, splits, garbage, limits."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.tunnel import NEED_DATA, PURPOSES, Preamble, PreambleReader, PreambleReply, encode

preambles = st.builds(
    Preamble,
    token=st.text(min_size=1, max_size=2000),
    purpose=st.sampled_from(sorted(PURPOSES)),
    target=st.text(max_size=512),
)
replies = st.builds(PreambleReply, ok=st.booleans(), error=st.text(max_size=100), token=st.text(max_size=2000))


def read_all(expect, chunks):
    reader = PreambleReader(expect)
    event = NEED_DATA
    for chunk in chunks:
        reader.receive_data(chunk)
        event = reader.next_event()
        if event is not NEED_DATA:
            break
    return reader, event


@settings(max_examples=200, deadline=None)
@given(preambles, st.binary(max_size=50))
def test_preamble_round_trips_whole_and_byte_by_byte(preamble, trailing):
    wire = encode(preamble) + trailing
    reader, whole = read_all(Preamble, [wire])
    assert whole == preamble
    assert reader.trailing_data() == trailing
    reader, split = read_all(Preamble, [wire[i : i + 1] for i in range(len(wire))])
    assert split == preamble
    # byte by byte, feeding stops at the preamble's last byte: nothing after it was read
    assert reader.trailing_data() == b""


@settings(max_examples=100, deadline=None)
@given(replies)
def test_reply_round_trips(reply):
    assert read_all(PreambleReply, [encode(reply)])[1] == reply


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_any_bytes_give_an_event_need_data_or_remote_error(data):
    """Fuzz: any bytes give a Preamble, NEED_DATA or a RemoteProtocolError, never another
    exception; and the same outcome fed whole or byte by byte."""

    def outcome(chunks):
        reader = PreambleReader(Preamble)
        try:
            for chunk in [*chunks, b""]:
                reader.receive_data(chunk)
                event = reader.next_event()
                if event is not NEED_DATA:
                    assert isinstance(event, Preamble), event
                    return event
            return NEED_DATA
        except RemoteProtocolError:
            return "refused"

    assert outcome([data]) == outcome([data[i : i + 1] for i in range(len(data))])


def test_declared_length_checked_before_buffering():
    reader = PreambleReader(Preamble, max_size=1024)
    with pytest.raises(RemoteProtocolError, match="exceeds"):
        reader.receive_data(struct.pack("<3sBBI", b"CRT", 1, 1, 10**9))


@pytest.mark.parametrize(
    ("wire", "message"),
    [
        (b"GET / HTTP/1.1\r\n\r\n", "bad magic"),
        (struct.pack("<3sBBI", b"CRT", 9, 1, 2) + b"{}", "version"),
        (struct.pack("<3sBBI", b"CRT", 1, 2, 2) + b"{}", "kind"),
        (struct.pack("<3sBBI", b"CRT", 1, 1, 2) + b"\xff\xfe", "UTF-8 JSON"),
        (struct.pack("<3sBBI", b"CRT", 1, 1, 2) + b"[]", "not a JSON object"),
        (struct.pack("<3sBBI", b"CRT", 1, 1, 2) + b"{}", "fields"),
    ],
)
def test_garbage_is_a_remote_protocol_error(wire, message):
    reader = PreambleReader(Preamble)
    with pytest.raises(RemoteProtocolError, match=message):
        reader.receive_data(wire)
        reader.next_event()


def test_bad_values_from_the_peer_are_remote_errors():
    body = b'{"token":"t","purpose":"teleport","target":""}'
    reader = PreambleReader(Preamble)
    reader.receive_data(struct.pack("<3sBBI", b"CRT", 1, 1, len(body)) + body)
    with pytest.raises(RemoteProtocolError, match="purpose"):
        reader.next_event()


def test_truncated_preamble_then_close_is_a_remote_error():
    wire = encode(Preamble(token="t", purpose="topic", target="x"))
    reader = PreambleReader(Preamble)
    reader.receive_data(wire[:-3])
    assert reader.next_event() is NEED_DATA
    reader.receive_data(b"")
    with pytest.raises(RemoteProtocolError, match="closed"):
        reader.next_event()


def test_local_misuse_is_a_local_error():
    with pytest.raises(LocalProtocolError):
        Preamble(token="", purpose="topic", target="")
    with pytest.raises(LocalProtocolError):
        PreambleReader(dict)  # type: ignore[arg-type]
    reader = PreambleReader(Preamble)
    with pytest.raises(LocalProtocolError):
        reader.trailing_data()
