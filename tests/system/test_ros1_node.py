"""Our node client and embedded master together, in-process on loopback sockets."""

from __future__ import annotations

import asyncio
import socket
import struct

import pytest

from cryptoros.ros1 import msgs, tcpros
from cryptoros.ros1.master import Master
from cryptoros.ros1.node import Node, RosApiError, XmlRpcClient, call
from cryptoros.ros1.xmlrpc import Request, make_multicall


@pytest.fixture
async def master():
    async with Master(port=0) as m:
        yield m


async def test_publish_subscribe_in_order_both_styles(master) -> None:
    async with Node("/talker", master.uri) as a, Node("/listener", master.uri) as b, Node("/cb", master.uri) as c:
        pub = await a.advertise("/chatter", "std_msgs/String")
        sub = await b.subscribe("/chatter", "std_msgs/String")
        seen = []
        await c.subscribe("/chatter", "std_msgs/String", lambda m: seen.append(m.data))
        await pub.wait_for_subscribers(2, 5)
        for i in range(1000):
            pub.publish(a.msg("std_msgs/String", data=f"m{i}"))
        got = []
        async for m in sub:
            got.append(m.data)
            if len(got) == 1000:
                break
        assert got == [f"m{i}" for i in range(1000)]
        for _ in range(100):
            if len(seen) == 1000:
                break
            await asyncio.sleep(0.02)
        assert seen == got


async def test_latching_and_late_subscriber(master) -> None:
    async with Node("/talker", master.uri) as a, Node("/late", master.uri) as b:
        pub = await a.advertise("/state", "std_msgs/String", latch=True)
        pub.publish(a.msg("std_msgs/String", data="first"))
        pub.publish(a.msg("std_msgs/String", data="latest"))
        sub = await b.subscribe("/state", "std_msgs/String")
        assert (await sub.get(5)).data == "latest"
        assert sub.connection_headers[0]["latching"] == "1"


async def test_publisher_update_when_publisher_comes_later(master) -> None:
    async with Node("/listener", master.uri) as b:
        sub = await b.subscribe("/later", "std_msgs/String")
        assert sub.num_connections == 0
        async with Node("/talker", master.uri) as a:
            pub = await a.advertise("/later", "std_msgs/String")
            await pub.wait_for_subscribers(1, 5)  # the master called publisherUpdate on /listener
            pub.publish(a.msg("std_msgs/String", data="hi"))
            assert (await sub.get(5)).data == "hi"
        for _ in range(100):  # the talker unregistered: the master told the listener
            if not sub.publishers:
                break
            await asyncio.sleep(0.02)
        assert sub.publishers == []


async def test_close_unregisters_everything(master) -> None:
    node = Node("/n", master.uri)
    await node.start()
    await node.advertise("/a", "std_msgs/String")
    await node.subscribe("/b", "std_msgs/String")
    await node.advertise_service("/s", "std_srvs/Trigger", lambda r: None)
    state = master.api_getSystemState("/x").value[2]
    assert state == [[["/a", ["/n"]]], [["/b", ["/n"]]], [["/s", ["/n"]]]]
    await node.close()
    assert master.api_getSystemState("/x").value[2] == [[], [], []]
    assert "/n" not in master.nodes


async def test_services_ok_and_error(master) -> None:
    async with Node("/srv", master.uri) as a, Node("/cli", master.uri) as b:
        Req = msgs.msg_class("std_srvs/SetBool_Request")
        Resp = msgs.msg_class("std_srvs/SetBool_Response")

        def handle(req):
            if not req.data:
                raise ValueError("refusing false")
            return Resp(success=True, message="done")

        await a.advertise_service("/toggle", "std_srvs/SetBool", handle)
        resp = await b.call_service("/toggle", "std_srvs/SetBool", Req(data=True))
        assert (resp.success, resp.message) == (True, "done")
        with pytest.raises(RosApiError, match="refusing false"):
            await b.call_service("/toggle", "std_srvs/SetBool", Req(data=False))
        with pytest.raises(RosApiError):
            await b.call_service("/missing", "std_srvs/SetBool", Req(data=True))


async def test_node_api(master) -> None:
    async with Node("/talker", master.uri) as a, Node("/listener", master.uri) as b:
        pub = await a.advertise("/chatter", "std_msgs/String")
        await b.subscribe("/chatter", "std_msgs/String")
        await pub.wait_for_subscribers(1, 5)
        assert isinstance(await call(a.uri, "getPid", "/x"), int)
        bus = await call(a.uri, "getBusInfo", "/x")
        assert bus[0][1:5] == ["/listener", "o", "TCPROS", "/chatter"]
        assert await call(a.uri, "getPublications", "/x") == [["/chatter", "std_msgs/String"]]
        proto = await call(a.uri, "requestTopic", "/x", "/chatter", [["TCPROS"]])
        assert proto == ["TCPROS", "127.0.0.1", a.tcpros_port]
        with pytest.raises(RosApiError):
            await call(a.uri, "requestTopic", "/x", "/nope", [["TCPROS"]])
        await call(a.uri, "shutdown", "/x", "bye")
        assert a.shutdown_requested.is_set() and a.shutdown_reason == "bye"


async def test_master_rules_and_multicall(master) -> None:
    api = "http://127.0.0.1:1/"
    assert await call(master.uri, "registerPublisher", "/p", "/t", "std_msgs/String", api) == []
    # unregister with the wrong caller_api does nothing
    assert await call(master.uri, "unregisterPublisher", "/p", "/t", "http://evil:2/") == 0
    client = XmlRpcClient(master.uri)
    try:
        mc = make_multicall([
            Request(method="unregisterPublisher", params=("/p", "/t", api)),
            Request(method="getParam", params=("/p", "/missing")),
        ])
        resp = await client.call_raw(mc.method, *mc.params)
        assert resp.value[0] == [[1, "Unregistered [/p] from [/t]", 1]]
        assert resp.value[1][0][0] == -1
        nested = Request(method="system.multicall", params=([{"methodName": "system.multicall", "params": [[]]}],))
        fault = await client.call_raw(nested.method, *nested.params)
        assert fault.code == 1 and "inside" in fault.string
    finally:
        await client.close()
    assert master.api_getSystemState("/x").value[2][0] == []


async def test_name_hijack_shuts_down_old_node(master) -> None:
    async with Node("/same", master.uri) as old, Node("/same", master.uri) as new:
        await old.advertise("/x", "std_msgs/String")
        await new.advertise("/y", "std_msgs/String")
        await asyncio.wait_for(old.shutdown_requested.wait(), 5)
        assert "same name" in old.shutdown_reason
        assert master.nodes["/same"] == new.uri


async def test_parameters(master) -> None:
    async with Node("/ns/node", master.uri) as n:
        await n.set_param("/robot/speed", 1.5)
        await n.set_param("gain", {"p": 1, "i": [0, 1]})
        assert await n.get_param("/robot") == {"speed": 1.5}
        assert await n.get_param("/ns/gain/i") == [0, 1]
        assert await call(master.uri, "hasParam", "/ns/node", "gain") is True
        assert await call(master.uri, "searchParam", "/ns/node", "gain") == "/ns/gain"
        assert "/ns/gain/p" in await call(master.uri, "getParamNames", "/x")
        await call(master.uri, "deleteParam", "/x", "/robot/speed")
        with pytest.raises(RosApiError):
            await n.get_param("/robot/speed")


async def test_bad_tcpros_headers_get_error_and_close(master) -> None:
    async with Node("/talker", master.uri) as a:
        await a.advertise("/chatter", "std_msgs/String")

        async def exchange(raw: bytes, closes: bool = True) -> dict[str, str]:
            reader, writer = await asyncio.open_connection("127.0.0.1", a.tcpros_port)
            try:
                writer.write(raw)
                await writer.drain()
                data = await asyncio.wait_for(reader.read(65536), 5)
                if closes:
                    rest = await asyncio.wait_for(reader.read(), 5)  # then the node closes
                    assert rest == b""
                return tcpros.decode_header(data[4:]).as_dict() if data else {}
            finally:
                writer.close()

        good = {"callerid": "/x", "md5sum": msgs.md5sum("std_msgs/String"), "topic": "/chatter", "type": "std_msgs/String"}
        no_topic = {k: v for k, v in good.items() if k != "topic"}
        assert "error" in await exchange(tcpros.encode_header(no_topic))
        assert "md5sum" in (await exchange(tcpros.encode_header({**good, "md5sum": "0" * 32})))["error"]
        assert "error" in await exchange(tcpros.encode_header({**good, "topic": "/other"}))
        field = b"topic/chatter"
        assert "error" in await exchange(struct.pack("<II", len(field) + 4, len(field)) + field)
        assert "exceeds" in (await exchange(struct.pack("<I", 1 << 30)))["error"]
        # the node still serves a good subscriber afterwards
        assert (await exchange(tcpros.encode_header(good), closes=False))["md5sum"] == good["md5sum"]


async def test_tcp_nodelay_is_honoured(master) -> None:
    async with Node("/talker", master.uri) as a, Node("/listener", master.uri) as b:
        pub = await a.advertise("/fast", "std_msgs/String")
        await b.subscribe("/fast", "std_msgs/String", tcp_nodelay=True)
        await pub.wait_for_subscribers(1, 5)
        (link,) = pub._links
        sock = link.transport.get_extra_info("socket")
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0


def test_cryptoros_master_on_a_busy_port_or_a_foreign_address_is_one_line():
    """Day 2: `cryptoros master` printed a traceback on a port in use or an address the
    host does not have; it says it in one line and exits 1."""
    from tests.support import run, script

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        for host, port_, needle in (("127.0.0.1", port, "address already in use"),
                                    ("10.254.254.254", 0, "no such address on this host")):
            result = run([script("cryptoros"), "master", "--host", host, "--port", str(port_), "--unsafe-expose"],
                         timeout=30)
            lines = result.stderr.strip().splitlines()
            assert result.returncode == 1 and len(lines) == 1 and needle in lines[0], result.stderr
