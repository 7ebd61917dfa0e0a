"""XML-RPC over HTTP/1.1 codec: framing, values, gzip, multicall, hostile input."""

from __future__ import annotations

import gzip
import math
import xmlrpc.client

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.ros1 import xmlrpc as x
from cryptoros.ros1.xmlrpc import NEED_DATA, ConnectionClosed, Fault, Request, Response, Role, XmlRpcConnection


def drain(conn: XmlRpcConnection) -> list:
    out = []
    while True:
        ev = conn.next_event()
        if ev is NEED_DATA:
            return out
        out.append(ev)
        if isinstance(ev, ConnectionClosed):
            return out


def feed(role: Role, data: bytes, chunk: int | None = None, eof: bool = True, **kw) -> list:
    conn = XmlRpcConnection(role, **kw)
    out = []
    step = chunk or max(1, len(data))
    for i in range(0, len(data), step):
        conn.receive_data(data[i : i + step])
        out += drain(conn)
    if eof:
        conn.receive_data(b"")
        out += drain(conn)
    return out


def http_request(body: bytes, extra: str = "") -> bytes:
    return (
        f"POST /RPC2 HTTP/1.1\r\nHost: 127.0.0.1:11311\r\nContent-Type: text/xml\r\n{extra}"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode() + body


ROSPY_CALL = xmlrpc.client.dumps(("/talker", "/chatter", "std_msgs/String", "http://127.0.0.1:4242/"), "registerPublisher").encode()


def test_rospy_request_split_header_and_body() -> None:
    conn = XmlRpcConnection(Role.SERVER)
    raw = http_request(ROSPY_CALL, "Accept-Encoding: gzip\r\n")
    head, body = raw.split(b"\r\n\r\n", 1)
    conn.receive_data(head + b"\r\n\r\n")
    assert conn.next_event() is NEED_DATA
    conn.receive_data(body[:10])
    assert conn.next_event() is NEED_DATA
    conn.receive_data(body[10:])
    req = conn.next_event()
    assert req == Request(
        method="registerPublisher",
        params=("/talker", "/chatter", "std_msgs/String", "http://127.0.0.1:4242/"),
        accept_gzip=True,
    )


def test_keep_alive_two_requests_and_response_readable_by_python() -> None:
    raw = http_request(ROSPY_CALL) + http_request(xmlrpc.client.dumps(("/n",), "getPid").encode())
    evs = feed(Role.SERVER, raw)
    assert [e.method for e in evs[:2]] == ["registerPublisher", "getPid"]
    assert evs[2] == ConnectionClosed()
    server = XmlRpcConnection(Role.SERVER)
    out = server.send(Response(value=[1, "ok", [1, 2.5, True, "s", {"a": [b"\x00"]}]]))
    body = out.split(b"\r\n\r\n", 1)[1]
    (value,), _ = xmlrpc.client.loads(body, use_builtin_types=True)
    assert value == [1, "ok", [1, 2.5, True, "s", {"a": [b"\x00"]}]]


def test_roscpp_untyped_values_and_i4() -> None:
    body = (
        b"<?xml version=\"1.0\"?>\r\n<methodResponse><params><param>"
        b"<value><array><data><value><i4>1</i4></value><value>ready on 127.0.0.1:3</value>"
        b"<value><array><data><value>TCPROS</value><value>127.0.0.1</value><value><i4>41234</i4></value>"
        b"</data></array></value></data></array></value></param></params></methodResponse>\r\n"
    )
    raw = b"HTTP/1.1 200 OK\r\nServer: XMLRPC++ 0.7\r\nContent-Type: text/xml\r\nContent-length: " + str(len(body)).encode() + b"\r\n\r\n" + body
    (resp,) = [e for e in feed(Role.CLIENT, raw) if not isinstance(e, ConnectionClosed)]
    assert resp.value == [1, "ready on 127.0.0.1:3", ["TCPROS", "127.0.0.1", 41234]]
    # re-serialized, rospy's xmlrpc.client reads it the same
    server = XmlRpcConnection(Role.SERVER)
    again = server.send(resp).split(b"\r\n\r\n", 1)[1]
    assert xmlrpc.client.loads(again)[0][0] == resp.value


def test_gzip_response_and_request() -> None:
    body = x.dumps_response(Response(value=[1, "x" * 5000, 0]))
    gz = gzip.compress(body)
    raw = b"HTTP/1.0 200 OK\r\nContent-Encoding: gzip\r\nContent-Length: %d\r\n\r\n" % len(gz) + gz
    (resp, closed) = feed(Role.CLIENT, raw, chunk=100)
    assert resp.value[1] == "x" * 5000 and resp.keep_alive is False
    # our server gzips when asked and allowed
    server = XmlRpcConnection(Role.SERVER, gzip_threshold=1400)
    server.receive_data(http_request(ROSPY_CALL, "Accept-Encoding: gzip\r\n"))
    server.next_event()
    out = server.send(Response(value=[1, "y" * 3000, 0]))
    assert b"Content-Encoding: gzip" in out
    assert feed(Role.CLIENT, out, eof=False)[0].value[1] == "y" * 3000


def test_response_without_content_length_reads_to_eof() -> None:
    body = x.dumps_response(Response(value=[1, "", 7]))
    evs = feed(Role.CLIENT, b"HTTP/1.0 200 OK\r\n\r\n" + body, chunk=9)
    assert evs[0].value == [1, "", 7]


def test_fault_roundtrip() -> None:
    server = XmlRpcConnection(Role.SERVER)
    out = server.send(Fault(code=-1, string="no such method"))
    (fault,) = feed(Role.CLIENT, out, eof=False)
    assert fault == Fault(code=-1, string="no such method")
    with pytest.raises(xmlrpc.client.Fault):
        xmlrpc.client.loads(out.split(b"\r\n\r\n", 1)[1])


def test_multicall_expand_and_reassemble() -> None:
    calls = [
        Request(method="unregisterSubscriber", params=("/l", "/chatter", "http://127.0.0.1:1/")),
        Request(method="unregisterPublisher", params=("/l", "/rosout", "http://127.0.0.1:1/")),
    ]
    mc = x.make_multicall(calls)
    body = x.dumps_call(mc.method, mc.params)
    # the same bytes as Python's own MultiCall would send
    ref = xmlrpc.client.dumps(([{"methodName": c.method, "params": list(c.params)} for c in calls],), "system.multicall")
    assert x.loads_call(ref.encode()) == x.loads_call(body)
    (req,) = feed(Role.SERVER, http_request(body), eof=False)
    assert x.expand_multicall(req) == calls
    resp = x.assemble_multicall([Response(value=[1, "ok", 1]), Fault(code=1, string="bad")])
    assert x.split_multicall_response(resp, 2) == [Response(value=[1, "ok", 1]), Fault(code=1, string="bad")]


def test_nested_multicall_refused() -> None:
    inner = {"methodName": "system.multicall", "params": [[{"methodName": "shutdown", "params": ["/x", "bye"]}]]}
    body = xmlrpc.client.dumps(([inner],), "system.multicall").encode()
    (req,) = feed(Role.SERVER, http_request(body), eof=False)
    with pytest.raises(RemoteProtocolError, match="inside"):
        x.expand_multicall(req)
    with pytest.raises(LocalProtocolError):
        x.make_multicall([req])


@pytest.mark.parametrize(
    "params",
    [(), ("notalist",), ([{"methodName": "a"}],), ([{"methodName": 3, "params": []}],), ([[1]],), ([], [])],
)
def test_bad_multicall_shapes(params) -> None:
    with pytest.raises(RemoteProtocolError):
        x.expand_multicall(Request(method="system.multicall", params=params))
    assert x.expand_multicall(Request(method="system.multicall", params=([],))) == []


BOMB = b"""<?xml version="1.0"?>
<!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
<!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">]>
<methodCall><methodName>getPid</methodName><params><param><value>&lol3;</value></param></params></methodCall>"""
XXE = b"""<?xml version="1.0"?>
<!DOCTYPE foo [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>
<methodCall><methodName>getPid</methodName><params><param><value>&xxe;</value></param></params></methodCall>"""


@pytest.mark.parametrize(
    "body",
    [
        BOMB,
        XXE,
        b"<methodCall><methodName>a</methodName><params><param><value>\xff\xfe</value></param></params></methodCall>",
        b"<methodCall><methodName>a</methodName>",
        b"<methodCall><params/></methodCall>",
        b"<methodResponse/>",
        b"<methodCall><methodName>a</methodName><params><param><value><int>x</int></value></param></params></methodCall>",
        b"<methodCall><methodName>a</methodName><params><param><value><weird/></value></param></params></methodCall>",
        b"<methodCall><methodName>a</methodName><params><param><value><boolean>2</boolean></value></param></params></methodCall>",
        b"<methodCall><methodName>a</methodName><params><param><value><int>99999999999999999999999</int></value></param></params></methodCall>",
        b"<methodCall><methodName>a</methodName><params><param>" + b"<value><array><data>" * 100 + b"</data></array></value>" * 100 + b"</param></params></methodCall>",
    ],
)
def test_hostile_bodies(body: bytes) -> None:
    with pytest.raises(RemoteProtocolError):
        feed(Role.SERVER, http_request(body))


def test_an_unknown_declared_encoding_is_a_protocol_error() -> None:
    """An insider's body declaring ``x-bogus`` raised LookupError out of the parser: an
    uncaught task exception and a 33-line traceback per stream, no denial counted."""
    body = b'<?xml version="1.0" encoding="x-bogus"?><methodCall><methodName>a</methodName></methodCall>'
    with pytest.raises(RemoteProtocolError, match="malformed XML"):
        feed(Role.SERVER, http_request(body))


def _datetime_call(text: str) -> bytes:
    return (b"<methodCall><methodName>setParam</methodName><params><param><value><dateTime.iso8601>"
            + text.encode() + b"</dateTime.iso8601></value></param></params></methodCall>")


def test_a_datetime_is_a_time_not_text_of_any_length() -> None:
    """A dateTime carried 900,000 characters past the parameter quota (charged as a
    number): only a time of fixed size is one."""
    for text in ("20261128T16:05:09", "2026-11-28T16:05:09", "2026-11-28T16:05:09.25Z", "20261128T160509+01:00"):
        (req, _) = feed(Role.SERVER, http_request(_datetime_call(text)))
        assert req.params == (xmlrpc.client.DateTime(text),)
    for text in ("x" * 900_000, "20261128T16:05:09" + "0" * 100, "yesterday", ""):
        with pytest.raises(RemoteProtocolError, match="dateTime"):
            feed(Role.SERVER, http_request(_datetime_call(text)))


def test_non_utf8_declared_encoding_is_decoded_properly() -> None:
    body = '<?xml version="1.0" encoding="iso-8859-1"?><methodCall><methodName>a</methodName><params><param><value>caf\xe9</value></param></params></methodCall>'.encode("latin-1")
    (req, _) = feed(Role.SERVER, http_request(body))
    assert req.params == ("café",)


def test_http_framing_limits() -> None:
    with pytest.raises(RemoteProtocolError, match="exceeds"):
        feed(Role.SERVER, b"POST / HTTP/1.1\r\nContent-Length: 1000001\r\n\r\n", max_body_size=1_000_000)
    with pytest.raises(RemoteProtocolError, match="exceeds"):
        feed(Role.SERVER, b"POST / HTTP/1.1\r\nX: " + b"a" * 20000, eof=False)
    with pytest.raises(RemoteProtocolError, match="Content-Length"):
        feed(Role.SERVER, b"POST / HTTP/1.1\r\nHost: x\r\n\r\n")
    with pytest.raises(RemoteProtocolError):
        feed(Role.SERVER, b"GET / HTTP/1.1\r\nContent-Length: 0\r\n\r\n")
    with pytest.raises(RemoteProtocolError):
        feed(Role.SERVER, b"POST / HTTP/1.1\r\nContent-Length: -5\r\n\r\n")
    with pytest.raises(RemoteProtocolError, match="middle"):
        feed(Role.SERVER, b"POST / HTTP/1.1\r\nContent-Length: 50\r\n\r\n<meth")
    with pytest.raises(RemoteProtocolError, match="status"):
        feed(Role.CLIENT, b"HTTP/1.1 500 Internal\r\nContent-Length: 0\r\n\r\n")
    with pytest.raises(RemoteProtocolError):
        feed(Role.SERVER, b"POST / HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n")


def test_gzip_bomb_refused() -> None:
    gz = gzip.compress(b"<" * 5_000_000)
    raw = b"POST / HTTP/1.1\r\nContent-Encoding: gzip\r\nContent-Length: %d\r\n\r\n" % len(gz) + gz
    with pytest.raises(RemoteProtocolError, match="inflates"):
        feed(Role.SERVER, raw, max_body_size=1_000_000)


def test_local_misuse() -> None:
    with pytest.raises(LocalProtocolError):
        XmlRpcConnection(Role.CLIENT).send(Response(value=1))
    with pytest.raises(LocalProtocolError):
        XmlRpcConnection(Role.SERVER).send(Request(method="a"))
    with pytest.raises(LocalProtocolError):
        x.dumps_call("a", [object()])
    with pytest.raises(LocalProtocolError):
        x.dumps_call("a", [math.inf])


# ---------------------------------------------------------------- properties

text = st.text(st.characters(blacklist_categories=("Cs", "Cc")), max_size=30)
scalars = st.one_of(
    st.integers(-(2**63), 2**63 - 1),
    st.booleans(),
    text,
    st.floats(allow_nan=False, allow_infinity=False),
    st.binary(max_size=20),
)
values = st.recursive(scalars, lambda c: st.one_of(st.lists(c, max_size=4), st.dictionaries(text, c, max_size=4)), max_leaves=15)


@given(st.text(st.characters(whitelist_categories=("L", "N"), whitelist_characters="._/"), min_size=1, max_size=20), st.lists(values, max_size=4), st.integers(1, 64))
def test_request_roundtrip_and_split_invariance(method, params, chunk) -> None:
    method = method.strip() or "m"
    client = XmlRpcConnection(Role.CLIENT)
    raw = client.send(Request(method=method, params=tuple(params)))
    whole = feed(Role.SERVER, raw)
    assert whole[0] == Request(method=method, params=tuple(params))
    assert feed(Role.SERVER, raw, chunk=chunk) == whole


@given(values, st.integers(1, 64))
def test_response_roundtrip(value, chunk) -> None:
    raw = XmlRpcConnection(Role.SERVER).send(Response(value=value))
    assert feed(Role.CLIENT, raw, chunk=chunk, eof=False) == [Response(value=value)]


@settings(max_examples=300)
@given(st.binary(max_size=300), st.sampled_from(list(Role)), st.integers(1, 40))
def test_any_bytes_give_events_or_remote_protocol_error(data, role, chunk) -> None:
    def attempt(step):
        try:
            return feed(role, data, chunk=step, max_body_size=200)
        except RemoteProtocolError:
            return "error"

    whole = attempt(None)
    assert attempt(chunk) == whole


@settings(max_examples=200)
@given(st.binary(max_size=200))
def test_any_body_after_valid_head(body) -> None:
    """Fuzz: any body behind a valid HTTP head is one Request or a RemoteProtocolError,
    never another exception (and never two calls out of one body)."""
    for prefix in (b"<methodCall><methodName>a</methodName><params><param>", b""):
        try:
            events = feed(Role.SERVER, http_request(prefix + body))
        except RemoteProtocolError:
            continue
        requests = [e for e in events if isinstance(e, Request)]
        assert len(requests) <= 1, events


def test_a_named_relay_path_is_accepted_and_read_as_the_root_other_paths_are_not() -> None:
    """rosmaster calls the master's interceptor's relays on the URI it was handed, whose
    path names the relay's target: accepted, and never passed on."""
    body = xmlrpc.client.dumps(("/master", "/chatter", []), "publisherUpdate").encode()
    named = http_request(body).replace(b"POST /RPC2 ", b"POST /cryptoros/127.0.0.3/11400/x/131074 ")
    (req,) = feed(Role.SERVER, named, eof=False)
    assert req.method == "publisherUpdate" and req.path == "/"
    for path in (b"/cryptoros/127.0.0.3/11400/q/1", b"/cryptoros/../etc", b"/other"):
        with pytest.raises(RemoteProtocolError):
            feed(Role.SERVER, http_request(body).replace(b"POST /RPC2 ", b"POST " + path + b" "))
