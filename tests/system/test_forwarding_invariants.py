"""What an interceptor sends on is rebuilt from what it parsed: the parsers' side,
without sockets.

The invariant, checked with generated input: whatever the XML-RPC/HTTP parser
accepts re-serializes to a canonical request that Python's ``http.server`` (the
server rosmaster and rospy run) parses as exactly one request with the same method
and parameters; whatever the TCPROS header parser accepts re-encodes to a header
rospy's own decoder reads back field for field. Everything else raises
RemoteProtocolError, nothing else.
"""

from __future__ import annotations

import io
import struct
import sys
import xmlrpc.client
from xmlrpc.server import SimpleXMLRPCDispatcher, SimpleXMLRPCRequestHandler

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cryptoros.errors import PolicyDenied, RemoteProtocolError
from cryptoros.ros1.rewrite import REDACTED, redact_node_reply, tcpros_only
from cryptoros.ros1.tcpros import (
    KNOWN_HEADER_FIELDS,
    ConnectionHeader,
    TCPROSConnection,
    canonical_header,
    encode_header,
)
from cryptoros.ros1.xmlrpc import (
    NEED_DATA,
    Request,
    Response,
    Role,
    XmlRpcConnection,
    dumps_call,
    expand_multicall,
    make_multicall,
)
from interceptor.pump import FrameCounter

# ---------------------------------------------------------------- Python's http.server as the judge


class _Recorder:
    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple]] = []

    def _dispatch(self, method: str, params: tuple):
        self.calls.append((method, params))
        return 0


class _InMemoryHandler(SimpleXMLRPCRequestHandler):
    """SimpleXMLRPCRequestHandler (rosmaster's and rospy's) fed from bytes; keep-alive
    as rosmaster's server (rospy keeps one connection to the master)."""

    protocol_version = "HTTP/1.1"

    def setup(self) -> None:
        self.rfile = io.BytesIO(self.request)
        self.wfile = io.BytesIO()

    def handle(self) -> None:
        self.close_connection = False
        while not self.close_connection and self.rfile.tell() < len(self.request):
            self.handle_one_request()

    def log_message(self, *args) -> None:
        pass


def http_server_calls(data: bytes) -> list[tuple[str, tuple]]:
    """Every call Python's XML-RPC server would run for these bytes on one connection."""
    recorder = _Recorder()
    dispatcher = SimpleXMLRPCDispatcher(allow_none=True, use_builtin_types=True)
    dispatcher.logRequests = False
    dispatcher.register_instance(recorder)
    dispatcher.register_multicall_functions()
    _InMemoryHandler(data, ("127.0.0.1", 1), dispatcher)
    return recorder.calls


def _plain(value):
    """Our values as xmlrpc.client returns them (lists, not tuples)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def parse_server(data: bytes) -> Request:
    conn = XmlRpcConnection(Role.SERVER)
    conn.receive_data(data)
    event = conn.next_event()
    if event is NEED_DATA:
        raise RemoteProtocolError("incomplete")
    assert isinstance(event, Request)
    return event


def canonical_bytes(request: Request) -> bytes:
    """What an interceptor sends upstream for a parsed request."""
    return XmlRpcConnection(Role.CLIENT).send(
        Request(method=request.method, params=request.params, path="/", keep_alive=False)
    )


def post(path: str, body: bytes, extra: str = "", version: str = "HTTP/1.1") -> bytes:
    return f"POST {path} {version}\r\nHost: x\r\nContent-Length: {len(body)}\r\n{extra}\r\n".encode("latin-1") + body


GETPID = dumps_call("getPid", ["/spy"])
SHUTDOWN = dumps_call("shutdown", ["/spy", "bye"])


# ---------------------------------------------------------------- the smuggling of finding 1


def test_a_second_call_hidden_in_the_request_path_is_refused() -> None:
    hidden = post("/", SHUTDOWN).decode()
    for path in (
        "/\tHTTP/1.1\n" + hidden,  # TAB, version, bare LF, a whole second request
        "/\t" + "HTTP/1.1\n",
        "/x\nContent-Length: 5",
        "/RPC2\x00",
    ):
        data = post(path, GETPID)
        with pytest.raises(RemoteProtocolError):
            parse_server(data)


@pytest.mark.parametrize(
    "data",
    [
        post("/", GETPID).replace(b"\r\n", b"\n"),  # bare LF everywhere
        post("/", GETPID, extra="X-A: 1\n"),  # bare LF in one field
        post("/", GETPID, extra="X-A: 1\r\n folded\r\n"),  # obs-fold
        post("/", GETPID, extra="X-A: a\x01b\r\n"),  # control character in a value
        post("/", GETPID, extra="X A: 1\r\n"),  # space in a name
        post("/", GETPID, extra="X-A: caf\xe9\r\n"),  # 8-bit
        post("/", GETPID, extra="".join(f"X-{i}: 1\r\n" for i in range(40))),  # too many fields
        post("/other", GETPID),  # a path no node advertises
        post("//", GETPID),
        post("/", GETPID, version="HTTP/2.0"),
        post("/", GETPID).replace(b"POST / ", b"POST  / "),
        post("/", GETPID).replace(b"POST", b"GET"),
        post("/", GETPID, extra="Content-Length: 3\r\n"),  # two different lengths
        post("/", GETPID, extra="Transfer-Encoding: chunked\r\n"),
        b"POST / HTTP/1.1\r\nContent-Length: 104857600\r\n\r\n",  # declared 100 MB: refused before the body
    ],
)
def test_strict_http_head(data: bytes) -> None:
    with pytest.raises(RemoteProtocolError):
        parse_server(data)


def test_the_paths_rospy_roscpp_and_xmlrpc_client_send_are_accepted() -> None:
    for path in ("/", "/RPC2"):
        assert parse_server(post(path, GETPID)).method == "getPid"
    with pytest.raises(Exception):
        Request(method="getPid", params=(), path="/\tHTTP/1.1")


def test_multicall_length_is_bounded() -> None:
    calls = [Request(method="getPid", params=("/a",))] * 300
    with pytest.raises(RemoteProtocolError, match="at most 256"):
        expand_multicall(make_multicall(calls))
    assert len(expand_multicall(make_multicall(calls[:256]))) == 256


# ---------------------------------------------------------------- the invariant, fuzzed

_names = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), min_size=1, max_size=20)
_leaf = (
    st.integers(-(2**31), 2**31 - 1)
    | st.booleans()
    | st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00\ufffe\uffff"), max_size=30)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.binary(max_size=20)
)
_values = st.recursive(
    _leaf, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_names, inner, max_size=3), max_leaves=12
)
_evil_text = st.sampled_from(
    ["", "\t", "\n", "\r", "\r\n", " ", "\x00", "\x7f", "\xff", "HTTP/1.1", "Content-Length: 9", "/", "/RPC2", ":"]
)


@st.composite
def http_requests(draw) -> bytes:
    method = draw(st.sampled_from(["getPid", "setParam", "shutdown", "system.multicall", "lookupNode"]))
    params = draw(st.lists(_values, max_size=4))
    body = dumps_call(method, params)
    if draw(st.booleans()):  # mutate the body
        i = draw(st.integers(0, len(body)))
        body = body[:i] + draw(_evil_text).encode("latin-1") + body[i:]
    path = draw(st.sampled_from(["/", "/RPC2"])) + "".join(draw(st.lists(_evil_text, max_size=3)))
    version = draw(st.sampled_from(["HTTP/1.1", "HTTP/1.0", "HTTP/1.1 ", "HTTP/1.2"]))
    extra = "".join(
        f"{draw(st.sampled_from(['X-A', 'Connection', 'Accept-Encoding', 'X A', '']))}:{draw(_evil_text)}\r\n"
        for _ in range(draw(st.integers(0, 3)))
    )
    data = post(path, body, extra=extra, version=version)
    if draw(st.booleans()):  # something pipelined behind it
        data += post("/", SHUTDOWN)
    return data


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(http_requests())
def test_accepted_requests_reserialize_to_exactly_one_identical_call(data: bytes) -> None:
    try:
        request = parse_server(data)
        expanded = expand_multicall(request)  # the interceptor decides a multicall call by call
    except RemoteProtocolError:
        return
    if request.method == "system.multicall":
        calls = http_server_calls(canonical_bytes(make_multicall(expanded)))
        expected = [(c.method, _plain(list(c.params))) for c in expanded]
        assert [(m, _plain(list(p))) for m, p in calls] == expected
        return
    calls = http_server_calls(canonical_bytes(request))
    assert len(calls) == 1
    method, params = calls[0]
    assert method == request.method
    assert _plain(list(params)) == _plain(list(request.params))


def test_the_judge_runs_a_smuggled_call_so_the_invariant_has_teeth() -> None:
    """What the old parser accepted and forwarded (the peer's path copied upstream):
    Python's server reads the TAB as a separator and runs the hidden call."""
    hidden = b"<methodCall><methodName>shutdown</methodName><params><param><value>/spy</value></param></params></methodCall>"
    path = "/\tHTTP/1.1\nContent-Length: %d\n\n%s" % (len(hidden), hidden.decode())
    calls = http_server_calls(post(path, GETPID))
    assert "shutdown" in [m for m, _ in calls]
    with pytest.raises(RemoteProtocolError):
        parse_server(post(path, GETPID))


# ---------------------------------------------------------------- TCPROS headers (finding 3)


def _raw_header(fields: list[bytes]) -> bytes:
    body = b"".join(struct.pack("<I", len(f)) + f for f in fields)
    return struct.pack("<I", len(body)) + body


def test_a_header_of_60000_tiny_fields_under_the_size_limit_is_refused() -> None:
    conn = TCPROSConnection()
    conn.receive_data(_raw_header([b"a%d=" % i for i in range(60_000)]))
    with pytest.raises(RemoteProtocolError, match="more than 32 fields"):
        conn.next_event()


def test_repeated_header_field_is_refused() -> None:
    conn = TCPROSConnection()
    conn.receive_data(_raw_header([b"topic=/a", b"topic=/b"]))
    with pytest.raises(RemoteProtocolError, match="given twice"):
        conn.next_event()


def test_canonical_header_keeps_only_known_fields_in_order() -> None:
    header = ConnectionHeader(
        fields=(("x-evil", "1"), ("type", "std_msgs/String"), ("callerid", "/a"), ("topic", "/t"), ("md5sum", "*"))
    )
    assert canonical_header(header).fields == (
        ("callerid", "/a"), ("topic", "/t"), ("type", "std_msgs/String"), ("md5sum", "*"),
    )


_keys = st.sampled_from(list(KNOWN_HEADER_FIELDS) + ["x", "evil", "a b", "é"])
_header_values = st.text(st.characters(blacklist_categories=("Cs",)), max_size=40)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(_keys, _header_values), max_size=40), st.binary(max_size=30))
def test_accepted_tcpros_headers_reencode_to_what_rospy_reads(fields, noise) -> None:
    sys.path.append("/usr/lib/python3/dist-packages")
    rosgraph_network = pytest.importorskip("rosgraph.network")
    data = _raw_header([f"{k}={v}".encode() for k, v in fields]) + noise
    conn = TCPROSConnection()
    conn.receive_data(data)
    try:
        header = conn.next_event()
    except RemoteProtocolError:
        return
    if not isinstance(header, ConnectionHeader):
        return
    wire = encode_header(canonical_header(header))
    (length,) = struct.unpack_from("<I", wire)
    assert length == len(wire) - 4
    decoded = rosgraph_network.decode_ros_handshake_header(wire)
    expected = {k: v for k, v in header.fields if k in KNOWN_HEADER_FIELDS}
    assert decoded == expected


# ---------------------------------------------------------------- frames (finding 4)


def test_a_declared_frame_over_the_limit_is_refused_before_its_body() -> None:
    counter = FrameCounter(max_size=1024, what="robot_a /chatter")
    ok = struct.pack("<I", 3) + b"abc"
    assert counter.take(ok, 10) == (len(ok), 1)
    with pytest.raises(PolicyDenied, match="exceeds max_message_size 1024") as info:
        counter.take(struct.pack("<I", 2**31) + b"x" * 100, 10)
    assert info.value.reason == "message_too_large"


def test_a_length_prefix_split_across_reads_is_still_checked() -> None:
    counter = FrameCounter(max_size=1024)
    prefix = struct.pack("<I", 5000)
    assert counter.take(prefix[:2], 10) == (2, 1)
    with pytest.raises(PolicyDenied):
        counter.take(prefix[2:], 10)


def test_service_responses_are_walked_with_their_ok_byte() -> None:
    counter = FrameCounter(max_size=100, service_response=True)
    good = struct.pack("<BI", 1, 4) + b"abcd" + struct.pack("<BI", 0, 2) + b"no"
    assert counter.take(good, 10) == (len(good), 2)
    with pytest.raises(PolicyDenied, match="ok byte"):
        FrameCounter(service_response=True).take(struct.pack("<BI", 7, 1) + b"x", 10)
    with pytest.raises(PolicyDenied, match="max_message_size"):
        counter.take(struct.pack("<BI", 1, 101), 10)


# ---------------------------------------------------------------- UDPROS (finding 2) and leaks


def _request_topic(protocols) -> Request:
    return Request(method="requestTopic", params=("/spy", "/cppchat", protocols))


def test_udpros_only_is_refused_and_udp_with_tcp_fallback_becomes_tcpros() -> None:
    udp = ["UDPROS", b"header", "127.0.0.9", 4000, 1500]
    with pytest.raises(PolicyDenied) as info:
        tcpros_only(_request_topic([udp]))
    assert info.value.reason == "udpros_refused"
    assert tcpros_only(_request_topic([udp, ["TCPROS"]])).params[2] == [["TCPROS"]]
    assert tcpros_only(_request_topic([["TCPROS", "extra"]])).params[2] == [["TCPROS"]]
    with pytest.raises(PolicyDenied):
        tcpros_only(_request_topic([]))


def test_node_api_replies_to_peers_name_no_host_endpoint() -> None:
    uri = redact_node_reply(Request(method="getMasterUri", params=("/x",)),
                            Response(value=[1, "", "http://127.0.0.1:11311/"]), "cryptoros://master")
    assert uri.value[2] == "cryptoros://master"
    bus = redact_node_reply(
        Request(method="getBusInfo", params=("/x",)),
        Response(value=[1, "", [[1, "http://127.0.0.1:4444/", "i", "TCPROS", "/chatter", True,
                                 "TCPROS connection on port 5555 to [127.0.0.1:6666 on socket 7]"],
                                [2, "/listener", "o", "TCPROS", "/chatter", True, ""]]]),
        "cryptoros://master",
    )
    assert bus.value[2] == [[1, REDACTED, "i", "TCPROS", "/chatter", True], [2, "/listener", "o", "TCPROS", "/chatter", True]]
    assert "127.0.0.1" not in repr(bus.value)


def test_xmlrpc_strings_with_carriage_returns_survive_reserialization() -> None:
    request = Request(method="setParam", params=("/a", "/a/x", "line1\r\nline2\r"))
    (method, params), = [xmlrpc.client.loads(canonical_bytes(request).split(b"\r\n\r\n", 1)[1])[::-1]]
    assert method == "setParam" and params[2] == "line1\r\nline2\r"
