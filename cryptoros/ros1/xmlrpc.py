"""XML-RPC over HTTP/1.1, sans-IO: the master, parameter-server and node APIs of ROS 1.

:class:`XmlRpcConnection` is one side of one HTTP connection, h11-style:
``receive_data(bytes)`` only buffers (``b""`` = peer closed), ``next_event()``
returns a :class:`Request` (server role), a :class:`Response` or :class:`Fault`
(client role), :class:`ConnectionClosed`, or :data:`NEED_DATA`; ``send(event)``
returns the bytes to write. Bodies are framed by ``Content-Length`` across any
split of the writes (rospy often sends header and body separately), may be gzip
encoded (decompressed with the body cap applied to the output, so a gzip bomb is
refused), and are parsed with ``defusedxml`` with DTDs forbidden (no entity
expansion bombs, no external entities).

Values map to Python: ``<int>/<i4>/<i8>`` -> int, ``<boolean>`` -> bool,
``<double>`` -> float, ``<string>`` and roscpp's untyped ``<value>text</value>`` ->
str, ``<base64>`` -> bytes, ``<dateTime.iso8601>`` -> :class:`xmlrpc.client.DateTime`,
``<array>`` -> list, ``<struct>`` -> dict, ``<nil/>`` -> None. Serializing writes
``<int>`` (``<i8>`` out of 32-bit range), which rospy and roscpp both read.

``system.multicall`` is expanded into its calls (:func:`expand_multicall`) and
re-assembled (:func:`make_multicall`, :func:`assemble_multicall`,
:func:`split_multicall_response`); a multicall inside a multicall is refused.
"""

from __future__ import annotations

import base64
import binascii
import enum
import math
import re
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final
from xml.etree.ElementTree import Element, ParseError
from xmlrpc.client import DateTime

import defusedxml
import defusedxml.ElementTree as DET

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.sansio import NEED_DATA, ReceiveBuffer, TrailingData
from cryptoros.sansio import NeedData as _NeedData

__all__ = [
    "NEED_DATA",
    "Request",
    "Response",
    "Fault",
    "ConnectionClosed",
    "XmlRpcConnection",
    "Role",
    "dumps_call",
    "loads_call",
    "dumps_response",
    "loads_response",
    "expand_multicall",
    "make_multicall",
    "assemble_multicall",
    "split_multicall_response",
    "MULTICALL",
    "ALLOWED_PATHS",
    "request_path",
]

MULTICALL: Final = "system.multicall"
DEFAULT_MAX_BODY_SIZE: Final = 16 << 20
DEFAULT_MAX_HEAD_SIZE: Final = 16 << 10
MAX_DEPTH: Final = 64
#: an XML-RPC dateTime as rospy and roscpp write it (``20261128T16:05:09``), ISO 8601's
#: dashes, fraction and zone allowed: a fixed size, not text of any length
_DATETIME = re.compile(r"\d{4}-?\d{2}-?\d{2}T\d{2}:?\d{2}:?\d{2}(\.\d{1,9})?(Z|[+-]\d{2}:?\d{2})?")
#: Request paths accepted from a peer: what rospy, roscpp and xmlrpc.client send for
#: ``http://host:port/`` and ``http://host:port``. The path sent on is never the
#: peer's: callers set it from the URI the receiving node advertised.
ALLOWED_PATHS: Final = ("/", "/RPC2")
#: A relay URI the master's interceptor hands rosmaster names the relay's target in its
#: path (``/cryptoros/<host>/<port>/<x|t>/<id>``): accepted, and read as ``/``.
NAMED_RELAY_PATH: Final = re.compile(r"/cryptoros/[0-9A-Za-z.\-]{1,253}/[0-9]{1,5}/[xt]/[0-9]{1,14}")
DEFAULT_MAX_HEADER_FIELDS: Final = 32
MAX_HEADER_FIELD_SIZE: Final = 4096
#: Calls one ``system.multicall`` may hold (rospy's shutdown multicall holds one
#: ``unregister*`` per topic and service of the node).
DEFAULT_MAX_MULTICALL: Final = 256
_TOKEN = re.compile(r"[!#$%&'*+\-.^_`|~0-9A-Za-z]+")
# Anything but printable ASCII, SP, HTAB and CRLF pairs: bare CR, bare LF, NUL, DEL, 8-bit.
_HEAD_FORBIDDEN = re.compile(rb"[^\x20-\x7e\t\r\n]|\r(?!\n)|(?<!\r)\n")
_REQUEST_LINE = re.compile(r"(?P<method>[A-Z]{1,10}) (?P<path>[!-~]{1,256}) (?P<version>HTTP/1\.[01])")
_STATUS_LINE = re.compile(r"(?P<version>HTTP/1\.[01]) (?P<status>[0-9]{3})(?: (?P<reason>[\t !-~]*))?")
_SINGLE_HEADERS = frozenset({"content-length", "content-encoding", "transfer-encoding", "connection"})
I4_MIN, I4_MAX = -(2**31), 2**31 - 1
I8_MIN, I8_MAX = -(2**63), 2**63 - 1


# ---------------------------------------------------------------- events


@dataclass(frozen=True, kw_only=True)
class Request:
    """An XML-RPC call. ``path`` and ``keep_alive``/``accept_gzip`` come from HTTP."""

    method: str
    params: tuple = ()
    path: str = "/RPC2"
    keep_alive: bool = True
    accept_gzip: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.method, str) or not self.method:
            raise LocalProtocolError("Request.method must be a non-empty str")
        if not isinstance(self.params, tuple):
            object.__setattr__(self, "params", tuple(self.params))
        if self.path not in ALLOWED_PATHS:
            raise LocalProtocolError(f"request path {self.path!r:.40} is not one of {ALLOWED_PATHS}")


@dataclass(frozen=True, kw_only=True)
class Response:
    """A successful XML-RPC response: one value (ROS puts ``[code, msg, value]``)."""

    value: Any = None
    keep_alive: bool = True


@dataclass(frozen=True, kw_only=True)
class Fault:
    """An XML-RPC fault response."""

    code: int
    string: str
    keep_alive: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.code, bool) or not isinstance(self.code, int) or not isinstance(self.string, str):
            raise LocalProtocolError("Fault needs an int code and a str string")


@dataclass(frozen=True, kw_only=True)
class ConnectionClosed:
    """The peer closed the connection between messages."""


Event = Request | Response | Fault | ConnectionClosed


def request_path(uri_path: str) -> str:
    """The request path to send to a server advertised with a URI whose path is
    ``uri_path``: ``/RPC2`` when it says so, else ``/`` (what the server's own
    clients send). Never a path a peer wrote."""
    return "/RPC2" if uri_path.rstrip("/") == "/RPC2" else "/"


# ---------------------------------------------------------------- values -> XML


def _escape(text: str) -> str:
    # A raw CR would be normalized away by the receiver's XML parser: keep it as a reference.
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace("\r", "&#13;")


def _dump_value(value: Any, out: list[str], depth: int = 0) -> None:
    if depth > MAX_DEPTH:
        raise LocalProtocolError("value nested too deeply")
    if value is True or value is False:
        out.append(f"<value><boolean>{int(value)}</boolean></value>")
    elif isinstance(value, int):
        if I4_MIN <= value <= I4_MAX:
            out.append(f"<value><int>{value}</int></value>")
        elif I8_MIN <= value <= I8_MAX:
            out.append(f"<value><i8>{value}</i8></value>")
        else:
            raise LocalProtocolError(f"int out of XML-RPC range: {value}")
    elif isinstance(value, str):
        out.append(f"<value><string>{_escape(value)}</string></value>")
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise LocalProtocolError("XML-RPC cannot carry inf or nan")
        out.append(f"<value><double>{value!r}</double></value>")
    elif isinstance(value, (list, tuple)):
        out.append("<value><array><data>")
        for item in value:
            _dump_value(item, out, depth + 1)
        out.append("</data></array></value>")
    elif isinstance(value, dict):
        out.append("<value><struct>")
        for key, item in value.items():
            if not isinstance(key, str):
                raise LocalProtocolError("struct keys must be str")
            out.append(f"<member><name>{_escape(key)}</name>")
            _dump_value(item, out, depth + 1)
            out.append("</member>")
        out.append("</struct></value>")
    elif isinstance(value, (bytes, bytearray, memoryview)):
        out.append(f"<value><base64>{base64.b64encode(bytes(value)).decode()}</base64></value>")
    elif isinstance(value, DateTime):
        out.append(f"<value><dateTime.iso8601>{_escape(value.value)}</dateTime.iso8601></value>")
    elif value is None:
        out.append("<value><nil/></value>")
    else:
        raise LocalProtocolError(f"cannot marshal {type(value).__name__}")


def dumps_call(method: str, params: Sequence[Any]) -> bytes:
    out = ["<?xml version='1.0'?>\n<methodCall>\n<methodName>", _escape(method), "</methodName>\n<params>\n"]
    for p in params:
        out.append("<param>\n")
        _dump_value(p, out)
        out.append("\n</param>\n")
    out.append("</params>\n</methodCall>\n")
    return "".join(out).encode("utf-8")


def dumps_response(event: Response | Fault) -> bytes:
    out = ["<?xml version='1.0'?>\n<methodResponse>\n"]
    if isinstance(event, Fault):
        out.append("<fault>\n")
        _dump_value({"faultCode": event.code, "faultString": event.string}, out)
        out.append("\n</fault>\n")
    else:
        out.append("<params>\n<param>\n")
        _dump_value(event.value, out)
        out.append("\n</param>\n</params>\n")
    out.append("</methodResponse>\n")
    return "".join(out).encode("utf-8")


# ---------------------------------------------------------------- XML -> values


def _parse_xml(body: bytes) -> Element:
    try:
        return DET.fromstring(body, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except defusedxml.DefusedXmlException as err:
        raise RemoteProtocolError(f"forbidden XML construct: {type(err).__name__}") from err
    except (ParseError, ValueError, UnicodeError, LookupError) as err:  # LookupError: an unknown encoding
        raise RemoteProtocolError(f"malformed XML: {err}") from err


def _text(el: Element) -> str:
    if len(el):
        raise RemoteProtocolError(f"unexpected child elements in <{el.tag}>")
    return el.text or ""


def _load_value(el: Element, depth: int = 0) -> Any:
    if el.tag != "value":
        raise RemoteProtocolError(f"expected <value>, got <{el.tag}>")
    if depth > MAX_DEPTH:
        raise RemoteProtocolError("value nested too deeply")
    children = list(el)
    if not children:
        return el.text or ""  # roscpp: <value>text</value> is a string
    if len(children) != 1 or (el.text and el.text.strip()):
        raise RemoteProtocolError("<value> must hold exactly one typed element")
    typ = children[0]
    tag = typ.tag
    try:
        if tag in ("int", "i4", "i8"):
            n = int(_text(typ).strip())
            if not I8_MIN <= n <= I8_MAX:
                raise RemoteProtocolError("integer out of range")
            return n
        if tag == "string":
            return _text(typ)
        if tag == "boolean":
            t = _text(typ).strip()
            if t not in ("0", "1"):
                raise RemoteProtocolError(f"bad boolean {t!r}")
            return t == "1"
        if tag == "double":
            x = float(_text(typ).strip())
            return x
        if tag == "array":
            datas = list(typ)
            if len(datas) != 1 or datas[0].tag != "data":
                raise RemoteProtocolError("<array> must hold one <data>")
            return [_load_value(v, depth + 1) for v in datas[0]]
        if tag == "struct":
            out: dict[str, Any] = {}
            for member in typ:
                if member.tag != "member":
                    raise RemoteProtocolError(f"unexpected <{member.tag}> in <struct>")
                parts = {c.tag: c for c in member}
                if len(member) != 2 or "name" not in parts or "value" not in parts:
                    raise RemoteProtocolError("<member> needs one <name> and one <value>")
                out[_text(parts["name"])] = _load_value(parts["value"], depth + 1)
            return out
        if tag == "base64":
            return base64.b64decode(_text(typ).encode("ascii"), validate=False)
        if tag == "dateTime.iso8601":
            text = _text(typ).strip()
            if not _DATETIME.fullmatch(text):
                raise RemoteProtocolError(f"bad <dateTime.iso8601> {text[:40]!r}")
            return DateTime(text)
        if tag == "nil":
            return None
    except (ValueError, binascii.Error, UnicodeError) as err:
        raise RemoteProtocolError(f"bad <{tag}> value: {err}") from err
    raise RemoteProtocolError(f"unknown XML-RPC type <{tag}>")


def _load_params(el: Element | None) -> tuple:
    if el is None:
        return ()
    out = []
    for param in el:
        if param.tag != "param" or len(param) != 1:
            raise RemoteProtocolError("<params> must hold <param> elements with one <value>")
        out.append(_load_value(param[0]))
    return tuple(out)


def loads_call(body: bytes) -> tuple[str, tuple]:
    """Parse a ``<methodCall>`` body into ``(method, params)``."""
    root = _parse_xml(body)
    if root.tag != "methodCall":
        raise RemoteProtocolError(f"expected <methodCall>, got <{root.tag}>")
    name = root.find("methodName")
    if name is None or not (name.text or "").strip():
        raise RemoteProtocolError("<methodCall> without <methodName>")
    for child in root:
        if child.tag not in ("methodName", "params"):
            raise RemoteProtocolError(f"unexpected <{child.tag}> in <methodCall>")
    return name.text.strip(), _load_params(root.find("params"))


def loads_response(body: bytes) -> Response | Fault:
    """Parse a ``<methodResponse>`` body."""
    root = _parse_xml(body)
    if root.tag != "methodResponse" or len(root) != 1:
        raise RemoteProtocolError("expected <methodResponse> with one child")
    child = root[0]
    if child.tag == "fault":
        if len(child) != 1:
            raise RemoteProtocolError("<fault> must hold one <value>")
        value = _load_value(child[0])
        if not isinstance(value, dict) or not isinstance(value.get("faultCode"), int):
            raise RemoteProtocolError("fault without an int faultCode")
        return Fault(code=value["faultCode"], string=str(value.get("faultString", "")))
    if child.tag != "params":
        raise RemoteProtocolError(f"unexpected <{child.tag}> in <methodResponse>")
    params = _load_params(child)
    if len(params) != 1:
        raise RemoteProtocolError(f"a response holds one value, not {len(params)}")
    return Response(value=params[0])


# ---------------------------------------------------------------- multicall


def expand_multicall(request: Request, *, max_calls: int = DEFAULT_MAX_MULTICALL) -> list[Request]:
    """The calls inside a ``system.multicall`` (or ``[request]`` for any other call).
    A multicall inside a multicall, or of more than ``max_calls`` calls, is refused."""
    if request.method != MULTICALL:
        return [request]
    if len(request.params) != 1 or not isinstance(request.params[0], list):
        raise RemoteProtocolError("system.multicall takes one array of calls")
    if len(request.params[0]) > max_calls:
        raise RemoteProtocolError(f"system.multicall of {len(request.params[0])} calls; at most {max_calls}")
    calls = []
    for item in request.params[0]:
        if not isinstance(item, dict) or set(item) != {"methodName", "params"}:
            raise RemoteProtocolError("a multicall entry is a struct of methodName and params")
        method, params = item["methodName"], item["params"]
        if not isinstance(method, str) or not method or not isinstance(params, list):
            raise RemoteProtocolError("a multicall entry needs a str methodName and an array of params")
        if method == MULTICALL:
            raise RemoteProtocolError("system.multicall inside system.multicall")
        calls.append(
            Request(
                method=method,
                params=tuple(params),
                path=request.path,
                keep_alive=request.keep_alive,
                accept_gzip=request.accept_gzip,
            )
        )
    return calls


def make_multicall(calls: Sequence[Request], *, like: Request | None = None) -> Request:
    """Re-assemble calls (after rewriting) into one ``system.multicall``."""
    entries = []
    for call in calls:
        if call.method == MULTICALL:
            raise LocalProtocolError("system.multicall inside system.multicall")
        entries.append({"methodName": call.method, "params": list(call.params)})
    kw = {} if like is None else {"path": like.path, "keep_alive": like.keep_alive, "accept_gzip": like.accept_gzip}
    return Request(method=MULTICALL, params=(entries,), **kw)


def assemble_multicall(results: Sequence[Response | Fault], *, keep_alive: bool = True) -> Response:
    """One response to a multicall: ``[value]`` per success, a fault struct per fault."""
    out: list[Any] = []
    for r in results:
        if isinstance(r, Fault):
            out.append({"faultCode": r.code, "faultString": r.string})
        else:
            out.append([r.value])
    return Response(value=out, keep_alive=keep_alive)


def split_multicall_response(response: Response | Fault, count: int | None = None) -> list[Response | Fault]:
    """The per-call results of a multicall response (inverse of :func:`assemble_multicall`)."""
    if isinstance(response, Fault):
        raise RemoteProtocolError(f"multicall failed as a whole: {response.string}")
    if not isinstance(response.value, list):
        raise RemoteProtocolError("a multicall response is an array")
    if count is not None and len(response.value) != count:
        raise RemoteProtocolError(f"multicall response has {len(response.value)} results for {count} calls")
    out: list[Response | Fault] = []
    for item in response.value:
        if isinstance(item, list) and len(item) == 1:
            out.append(Response(value=item[0], keep_alive=response.keep_alive))
        elif isinstance(item, dict) and isinstance(item.get("faultCode"), int) and not isinstance(item["faultCode"], bool):
            out.append(Fault(code=item["faultCode"], string=str(item.get("faultString", "")), keep_alive=response.keep_alive))
        else:
            raise RemoteProtocolError("a multicall result is [value] or a fault struct")
    return out


# ---------------------------------------------------------------- HTTP framing


class Role(enum.Enum):
    SERVER = "server"  # receives Requests, sends Responses/Faults
    CLIENT = "client"  # sends Requests, receives Responses/Faults


class _State(enum.Enum):
    HEAD = "head"
    BODY = "body"
    BODY_TO_EOF = "body_to_eof"
    CLOSED = "closed"
    ERROR = "error"


@dataclass
class _Head:
    first_line: str
    headers: dict[str, str] = field(default_factory=dict)


def _gunzip(data: bytes, limit: int) -> bytes:
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        out = d.decompress(data, limit + 1)
        if len(out) > limit or d.unconsumed_tail:
            raise RemoteProtocolError(f"gzip body inflates beyond the limit {limit}")
        out += d.flush()
    except zlib.error as err:
        raise RemoteProtocolError(f"bad gzip body: {err}") from err
    if len(out) > limit:
        raise RemoteProtocolError(f"gzip body inflates beyond the limit {limit}")
    if not d.eof:
        raise RemoteProtocolError("truncated gzip body")
    return out


class XmlRpcConnection:
    """One side of an HTTP/1.1 connection carrying XML-RPC.

    ``role=Role.SERVER`` parses requests and serializes responses;
    ``role=Role.CLIENT`` serializes requests and parses responses. Limits are
    constructor arguments; a declared ``Content-Length`` over ``max_body_size`` is
    refused before any of the body is buffered. ``gzip_threshold`` (server role)
    gzips responses at least that large when the client accepts gzip (None: never).
    """

    def __init__(
        self,
        role: Role,
        *,
        host: str = "localhost",
        max_body_size: int = DEFAULT_MAX_BODY_SIZE,
        max_head_size: int = DEFAULT_MAX_HEAD_SIZE,
        max_header_fields: int = DEFAULT_MAX_HEADER_FIELDS,
        gzip_threshold: int | None = None,
        user_agent: str = "cryptoros",
    ) -> None:
        self.role = role
        self.max_header_fields = max_header_fields
        self.host = host
        self.max_body_size = max_body_size
        self.max_head_size = max_head_size
        self.gzip_threshold = gzip_threshold
        self.user_agent = user_agent
        self._rb = ReceiveBuffer()
        self._state = _State.HEAD
        self._head: _Head | None = None
        self._length = 0
        self._last_accept_gzip = False

    # -- input
    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Buffer bytes from the peer; ``b""`` means the peer closed."""
        self._rb.feed(data)

    @property
    def trailing_data(self) -> TrailingData:
        """``(data, closed)``: bytes buffered but not parsed yet, and whether EOF was seen."""
        return self._rb.trailing()

    def next_event(self) -> Event | _NeedData:
        if self._state is _State.ERROR:
            raise RemoteProtocolError("connection already failed")
        if self._state is _State.CLOSED:
            return ConnectionClosed()
        try:
            return self._next()
        except RemoteProtocolError:
            self._state = _State.ERROR
            raise

    def _next(self) -> Event | _NeedData:
        if self._state is _State.HEAD:
            # tolerate blank lines between messages (RFC 9112 section 2.2)
            while self._rb.data[:2] == b"\r\n":
                del self._rb.data[:2]
            end = self._rb.data.find(b"\r\n\r\n")
            if end < 0:
                if len(self._rb.data) > self.max_head_size:
                    raise RemoteProtocolError(f"HTTP head exceeds {self.max_head_size} bytes")
                if self._rb.closed:
                    if self._rb.data:
                        raise RemoteProtocolError("connection closed in the middle of an HTTP head")
                    self._state = _State.CLOSED
                    return ConnectionClosed()
                return NEED_DATA
            if end > self.max_head_size:
                raise RemoteProtocolError(f"HTTP head exceeds {self.max_head_size} bytes")
            raw = self._rb.maybe_extract(end)
            assert raw is not None
            self._rb.discard(4)
            self._head = self._parse_head(raw)
            length = self._head.headers.get("content-length")
            if "transfer-encoding" in self._head.headers:
                raise RemoteProtocolError("Transfer-Encoding is not supported (ROS sends Content-Length)")
            if length is None:
                if self.role is Role.SERVER:
                    raise RemoteProtocolError("request without Content-Length")
                self._state = _State.BODY_TO_EOF
            else:
                if not length.isdigit() or len(length) > 18:
                    raise RemoteProtocolError(f"bad Content-Length {length[:20]!r}")
                self._length = int(length)
                if self._length > self.max_body_size:
                    raise RemoteProtocolError(f"declared body of {self._length} bytes exceeds {self.max_body_size}")
                self._state = _State.BODY
        if self._state is _State.BODY:
            body = self._rb.maybe_extract(self._length)
            if body is None:
                if self._rb.closed:
                    raise RemoteProtocolError("connection closed in the middle of a body")
                return NEED_DATA
            return self._finish(body)
        # BODY_TO_EOF
        if len(self._rb) > self.max_body_size:
            raise RemoteProtocolError(f"body exceeds {self.max_body_size} bytes")
        if not self._rb.closed:
            return NEED_DATA
        return self._finish(self._rb.take_all())

    def _parse_head(self, raw: bytes) -> _Head:
        """Strict RFC 9112 head: CRLF lines only, no control characters, no obs-fold,
        header names are tokens, a bounded number of fields, and (server role) a
        request line of exactly ``POST SP path SP version`` with ``path`` from
        :data:`ALLOWED_PATHS`."""
        if _HEAD_FORBIDDEN.search(raw):
            raise RemoteProtocolError("control character, bare CR/LF or non-ASCII byte in the HTTP head")
        text = raw.decode("ascii")
        lines = text.split("\r\n")
        if len(lines) - 1 > self.max_header_fields:
            raise RemoteProtocolError(f"more than {self.max_header_fields} HTTP header fields")
        head = _Head(first_line=lines[0])
        for line in lines[1:]:
            if line[:1] in (" ", "\t"):
                raise RemoteProtocolError("obsolete line folding in the HTTP head")
            name, sep, value = line.partition(":")
            if not sep or not _TOKEN.fullmatch(name):
                raise RemoteProtocolError(f"bad HTTP header line {line[:60]!r}")
            if len(line) > MAX_HEADER_FIELD_SIZE:
                raise RemoteProtocolError(f"HTTP header field over {MAX_HEADER_FIELD_SIZE} bytes")
            key = name.lower()
            value = value.strip(" \t")
            if key in _SINGLE_HEADERS and key in head.headers and head.headers[key] != value:
                raise RemoteProtocolError(f"conflicting {name} headers")
            head.headers[key] = value
        if self.role is Role.SERVER:
            m = _REQUEST_LINE.fullmatch(head.first_line)
            if m is None:
                raise RemoteProtocolError(f"bad request line {head.first_line[:80]!r}")
            if m["method"] != "POST":
                raise RemoteProtocolError(f"XML-RPC needs POST, got {m['method'][:10]!r}")
            if m["path"] not in ALLOWED_PATHS and not NAMED_RELAY_PATH.fullmatch(m["path"]):
                raise RemoteProtocolError(f"request path {m['path'][:40]!r} is not one of {', '.join(ALLOWED_PATHS)}")
        else:
            m = _STATUS_LINE.fullmatch(head.first_line)
            if m is None:
                raise RemoteProtocolError(f"bad status line {head.first_line[:80]!r}")
            if m["status"] != "200":
                raise RemoteProtocolError(f"HTTP status {m['status']} {m['reason'][:40]}")
        return head

    def _finish(self, body: bytes) -> Event:
        head = self._head
        assert head is not None
        self._head = None
        self._state = _State.HEAD
        enc = head.headers.get("content-encoding", "identity").lower()
        if enc == "gzip":
            body = _gunzip(body, self.max_body_size)
        elif enc not in ("identity", ""):
            raise RemoteProtocolError(f"unsupported Content-Encoding {enc[:20]!r}")
        version = head.first_line.split(" ")[2 if self.role is Role.SERVER else 0]
        conn = head.headers.get("connection", "").lower()
        keep_alive = "close" not in conn and (version == "HTTP/1.1" or "keep-alive" in conn)
        if self.role is Role.SERVER:
            method, params = loads_call(body)
            accept = "gzip" in head.headers.get("accept-encoding", "").lower()
            self._last_accept_gzip = accept
            return Request(
                method=method,
                params=params,
                path=path if (path := head.first_line.split(" ")[1]) in ALLOWED_PATHS else "/",
                keep_alive=keep_alive,
                accept_gzip=accept,
            )
        resp = loads_response(body)
        if not keep_alive:
            resp = type(resp)(**{**resp.__dict__, "keep_alive": False})
        return resp

    # -- output
    def send(self, event: Event) -> bytes:
        if isinstance(event, Request):
            if self.role is not Role.CLIENT:
                raise LocalProtocolError("a server does not send requests")
            body = dumps_call(event.method, event.params)
            lines = [
                f"POST {event.path} HTTP/1.1",
                f"Host: {self.host}",
                f"User-Agent: {self.user_agent}",
                "Content-Type: text/xml",
                f"Content-Length: {len(body)}",
            ]
            if event.accept_gzip:
                lines.append("Accept-Encoding: gzip")
            if not event.keep_alive:
                lines.append("Connection: close")
            return ("\r\n".join(lines) + "\r\n\r\n").encode("ascii") + body
        if isinstance(event, (Response, Fault)):
            if self.role is not Role.SERVER:
                raise LocalProtocolError("a client does not send responses")
            body = dumps_response(event)
            lines = ["HTTP/1.1 200 OK", "Server: cryptoros", "Content-Type: text/xml"]
            if self.gzip_threshold is not None and self._last_accept_gzip and len(body) >= self.gzip_threshold:
                c = zlib.compressobj(6, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
                body = c.compress(body) + c.flush()
                lines.append("Content-Encoding: gzip")
            lines.append(f"Content-Length: {len(body)}")
            if not event.keep_alive:
                lines.append("Connection: close")
            return ("\r\n".join(lines) + "\r\n\r\n").encode("ascii") + body
        if isinstance(event, ConnectionClosed):
            return b""
        raise LocalProtocolError(f"cannot send {event!r}")
