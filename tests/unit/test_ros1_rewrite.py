"""URI rewriting: pure functions over calls and responses, multicalls included."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cryptoros.errors import RemoteProtocolError
from cryptoros.ros1 import rewrite as rw
from cryptoros.ros1.xmlrpc import Fault, Request, Response, assemble_multicall, make_multicall, split_multicall_response

LOCAL = "http://127.0.0.1:40001/"
PUBLIC = "https://robot1.example:9443/n/talker"


def to_public(uri: str) -> str:
    return {LOCAL: PUBLIC, "rosrpc://127.0.0.1:40002": "rosrpcs://robot1.example:9443/s/add"}.get(uri, "UNMAPPED:" + uri)


@pytest.mark.parametrize(
    "method,params,index",
    [
        ("registerPublisher", ("/talker", "/chatter", "std_msgs/String", LOCAL), 3),
        ("registerSubscriber", ("/talker", "/chatter", "std_msgs/String", LOCAL), 3),
        ("unregisterPublisher", ("/talker", "/chatter", LOCAL), 2),
        ("unregisterSubscriber", ("/talker", "/chatter", LOCAL), 2),
    ],
)
def test_caller_api(method, params, index) -> None:
    out = rw.rewrite_caller_api(Request(method=method, params=params), to_public)
    assert out.params[index] == PUBLIC
    assert out.params[:index] == params[:index] and out.method == method


def test_register_service_rewrites_both() -> None:
    call = Request(method="registerService", params=("/srv", "/add", "rosrpc://127.0.0.1:40002", LOCAL))
    out = rw.rewrite_call(call, caller_api=to_public, service_api=to_public)
    assert out.params == ("/srv", "/add", "rosrpcs://robot1.example:9443/s/add", PUBLIC)
    un = rw.rewrite_call(Request(method="unregisterService", params=("/srv", "/add", "rosrpc://127.0.0.1:40002")), service_api=to_public)
    assert un.params[2] == "rosrpcs://robot1.example:9443/s/add"


def test_other_calls_untouched() -> None:
    call = Request(method="getParam", params=("/n", "/x"))
    assert rw.rewrite_call(call, caller_api=to_public, service_api=to_public, publisher_uri=to_public) is call


def test_multicall_rewritten_inside() -> None:
    calls = [
        Request(method="unregisterSubscriber", params=("/l", "/chatter", LOCAL)),
        Request(method="unregisterPublisher", params=("/l", "/rosout", LOCAL)),
        Request(method="getPid", params=("/l",)),
    ]
    out = rw.rewrite_call(make_multicall(calls), caller_api=to_public)
    entries = out.params[0]
    assert [e["params"][2] if e["methodName"] != "getPid" else None for e in entries] == [PUBLIC, PUBLIC, None]
    nested = make_multicall([calls[2]])
    bad = Request(method="system.multicall", params=([{"methodName": "system.multicall", "params": list(nested.params)}],))
    with pytest.raises(RemoteProtocolError):
        rw.rewrite_call(bad, caller_api=to_public)


def test_publisher_lists() -> None:
    call = Request(method="publisherUpdate", params=("/master", "/chatter", [LOCAL, "http://x:1/"]))
    assert rw.rewrite_call(call, publisher_uri=to_public).params[2] == [PUBLIC, "UNMAPPED:http://x:1/"]
    reg = Request(method="registerSubscriber", params=("/l", "/chatter", "std_msgs/String", "http://l:1/"))
    resp = rw.rewrite_response(reg, Response(value=[1, "Subscribed", [LOCAL]]), uri=to_public)
    assert resp.value == [1, "Subscribed", [PUBLIC]]
    with pytest.raises(RemoteProtocolError):
        rw.rewrite_publisher_list([LOCAL, 3], to_public)


def test_lookup_replies_and_failures() -> None:
    look = Request(method="lookupService", params=("/c", "/add"))
    reply = Response(value=[1, "rosrpc URI: [rosrpc://127.0.0.1:40002]", "rosrpc://127.0.0.1:40002"])
    rewritten = rw.rewrite_response(look, reply, uri=to_public).value
    assert rewritten[2].startswith("rosrpcs://") and rewritten[1] == "rosrpc URI"  # no hidden endpoint in the words
    failed = Response(value=[-1, "no provider", ""])
    assert rw.rewrite_response(look, failed, uri=to_public) is failed
    fault = Fault(code=1, string="x")
    assert rw.rewrite_response(look, fault, uri=to_public) is fault
    with pytest.raises(RemoteProtocolError):
        rw.rewrite_response(look, Response(value="garbage"), uri=to_public)


def test_tcpros_reply() -> None:
    req = Request(method="requestTopic", params=("/l", "/chatter", [["TCPROS"]]))
    resp = Response(value=[1, "ready on 127.0.0.1:40003", ["TCPROS", "127.0.0.1", 40003]])
    out = rw.rewrite_response(req, resp, tcpros=lambda h, p: ("10.0.0.5", p + 1))
    # the status message repeated the hidden endpoint (insider audit): fixed words now
    assert out.value == [1, "ready", ["TCPROS", "10.0.0.5", 40004]]
    for bad in (["UDPROS", "h", 1], ["TCPROS", "h", 0], ["TCPROS", "h", True], ["TCPROS", 5, 1], ["TCPROS", "h"]):
        with pytest.raises(RemoteProtocolError):
            rw.rewrite_tcpros_reply(Response(value=[1, "", bad]), lambda h, p: (h, p))


def test_multicall_response_rewrite() -> None:
    calls = [Request(method="lookupNode", params=("/a", "/b")), Request(method="getPid", params=("/a",))]
    resp = assemble_multicall([Response(value=[1, "", LOCAL]), Response(value=[1, "", 42])])
    out = rw.rewrite_response(make_multicall(calls), resp, uri=to_public)
    assert [r.value for r in split_multicall_response(out)] == [[1, "node api", PUBLIC], [1, "", 42]]
    with pytest.raises(RemoteProtocolError):
        rw.rewrite_response(make_multicall(calls), assemble_multicall([Response(value=1)]), uri=to_public)


@given(st.lists(st.sampled_from(list(rw.CALLER_API_INDEX)), max_size=6), st.text(max_size=10))
def test_identity_mapping_is_identity(methods, name) -> None:
    calls = [Request(method=m, params=(name, "/t", "x/Y", LOCAL)[: rw.CALLER_API_INDEX[m] + 1]) for m in methods]
    mc = make_multicall(calls)
    assert rw.rewrite_call(mc, caller_api=lambda u: u, service_api=lambda u: u) == mc
