"""The sans-IO base shared by the codecs: one NEED_DATA, one receive buffer, one
form of trailing_data (whole, byte by byte, with trailing data)."""

from __future__ import annotations

import pickle

import pytest

from cryptoros import sansio, tunnel
from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.ros1 import tcpros, xmlrpc
from cryptoros.sansio import NEED_DATA, ReceiveBuffer, TrailingData


def test_one_need_data_for_every_codec():
    assert tcpros.NEED_DATA is NEED_DATA
    assert xmlrpc.NEED_DATA is NEED_DATA
    assert tunnel.NEED_DATA is NEED_DATA
    assert sansio.NeedData() is NEED_DATA
    assert pickle.loads(pickle.dumps(NEED_DATA)) is NEED_DATA
    assert repr(NEED_DATA) == "NEED_DATA"


def test_receive_buffer_extracts_and_tracks_eof():
    buf = ReceiveBuffer()
    assert not buf and len(buf) == 0
    buf.feed(b"abc")
    buf.feed(b"")  # EOF
    buf.feed(b"")  # EOF twice is fine
    assert buf.closed
    with pytest.raises(LocalProtocolError):
        buf.feed(b"x")
    assert buf.maybe_extract(4) is None
    assert buf.maybe_extract(1) == b"a"
    assert bytes(buf) == b"bc"
    assert buf.trailing() == (b"bc", True)
    assert buf.take_all() == b"bc"
    assert len(buf) == 0
    with pytest.raises(LocalProtocolError):
        buf.maybe_extract(-1)


def test_receive_buffer_bound_is_checked_before_keeping_bytes():
    buf = ReceiveBuffer(max_size=4)
    buf.feed(b"abcd")
    with pytest.raises(RemoteProtocolError):
        buf.feed(b"e")
    assert bytes(buf) == b"abcd"
    with pytest.raises(LocalProtocolError):
        ReceiveBuffer(max_size=-1)


def test_trailing_data_is_data_and_closed_and_callable():
    t = TrailingData(b"xy", False)
    data, closed = t
    assert (data, closed) == (b"xy", False)
    assert t() == b"xy"


def _feeds(wire: bytes):
    yield [wire]
    yield [wire[i : i + 1] for i in range(len(wire))]


@pytest.mark.parametrize("trailing", [b"", b"rest of the stream"])
def test_tcpros_header_then_trailing_data(trailing):
    wire = tcpros.encode_header({"callerid": "/a", "topic": "/t"})
    for chunks in _feeds(wire):
        conn = tcpros.TCPROSConnection()
        for chunk in chunks:
            conn.receive_data(chunk)
        conn.receive_data(trailing)
        event = conn.next_event()
        assert isinstance(event, tcpros.ConnectionHeader)
        data, closed = conn.trailing_data
        assert data == trailing
        assert closed is (trailing == b"")


@pytest.mark.parametrize("trailing", [b"", b"\x01\x02"])
def test_tunnel_trailing_data_in_both_spellings(trailing):
    wire = tunnel.encode(tunnel.Preamble(token="t", purpose="topic", target="/x")) + trailing
    for chunks in _feeds(wire):
        reader = tunnel.PreambleReader(tunnel.Preamble)
        event = NEED_DATA
        for chunk in chunks:
            reader.receive_data(chunk)
            event = reader.next_event()
            if event is not NEED_DATA:
                break
        assert isinstance(event, tunnel.Preamble)
        if len(chunks) == 1:
            assert reader.trailing_data == (trailing, False)
            assert reader.trailing_data() == trailing
        else:
            assert reader.trailing_data == (b"", False)


def test_xmlrpc_trailing_data_after_a_request():
    client = xmlrpc.XmlRpcConnection(xmlrpc.Role.CLIENT)
    wire = client.send(xmlrpc.Request(method="getPid", params=("/a",)))
    for chunks in _feeds(wire + b"POST"):
        server = xmlrpc.XmlRpcConnection(xmlrpc.Role.SERVER)
        for chunk in chunks:
            server.receive_data(chunk)
        event = server.next_event()
        assert isinstance(event, xmlrpc.Request)
        assert server.trailing_data == (b"POST", False)
