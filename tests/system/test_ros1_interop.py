"""Interop with real ROS 1 (Debian's ros_comm): rospy, roscpp, rostopic, rosnode, rosmaster.

Real processes on loopback with free ports; every process is stopped in a finally and
every wait is bounded. rospy nodes run under /usr/bin/python3.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from cryptoros.ros1 import msgs
from cryptoros.ros1.node import Node
from tests.support import REPO, free_port, require, stop, wait_for_port

pytestmark = [pytest.mark.ros1]

NODES = Path(__file__).parents[1] / "ros1_nodes"
SYS_PY = "/usr/bin/python3"
STRING_MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"


def ros_env(master_uri: str, home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROS_")}
    env.update(ROS_MASTER_URI=master_uri, ROS_IP="127.0.0.1", ROS_HOME=str(home), PYTHONUNBUFFERED="1")
    env.pop("PYTHONPATH", None)
    return env


@pytest.fixture(scope="module")
def ros_home(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("ros_home")


@pytest.fixture(scope="module")
def rosmaster(ros_home) -> str:
    """Debian's real rosmaster, shared by this module."""
    path = require("rosmaster")["rosmaster"]
    port = free_port()
    proc = subprocess.Popen(
        [path, "--core", "-p", str(port)],
        env=ros_env(f"http://127.0.0.1:{port}", ros_home),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for_port("127.0.0.1", port, 15, proc)
        yield f"http://127.0.0.1:{port}/"
    finally:
        stop(proc)


@pytest.fixture(scope="module")
def our_master(ros_home) -> str:
    """`cryptoros master` (our embedded master) as its own process."""
    require("rosmaster")  # the clients of this master are real ROS tools
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cryptoros.cli", "master", "--port", str(port)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for_port("127.0.0.1", port, 15, proc)
        yield f"http://127.0.0.1:{port}/"
    finally:
        stop(proc)


@contextlib.asynccontextmanager
async def process(*args: str, env: dict[str, str]) -> AsyncIterator[asyncio.subprocess.Process]:
    proc = await asyncio.create_subprocess_exec(
        *args, env=env, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT
    )
    try:
        yield proc
    finally:
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(proc.wait(), 5)
            except asyncio.TimeoutError:
                proc.kill()
                await proc.wait()


async def read_until(proc: asyncio.subprocess.Process, pattern: str, timeout: float, seen: list[str]) -> str:
    async def go() -> str:
        while True:
            line = await proc.stdout.readline()
            if not line:
                raise AssertionError(f"process ended before {pattern!r}; output:\n" + "".join(seen))
            text = line.decode(errors="replace")
            seen.append(text)
            if re.search(pattern, text):
                return text

    try:
        return await asyncio.wait_for(go(), timeout)
    except asyncio.TimeoutError:
        raise AssertionError(f"no {pattern!r} within {timeout}s; output:\n" + "".join(seen)) from None


async def sh(*args: str, env: dict[str, str], timeout: float = 20) -> str:
    """Run a ROS command line tool without blocking the loop (our nodes must answer it)."""
    async with process(*args, env=env) as proc:
        try:
            out, _ = await asyncio.wait_for(proc.communicate(), timeout)
        except asyncio.TimeoutError:
            raise AssertionError(f"{args} did not finish within {timeout}s") from None
        text = out.decode(errors="replace")
        assert proc.returncode == 0, f"{args} exited {proc.returncode}:\n{text}"
        return text


# ----------------------------------------------------------------- our nodes vs real rospy, real rosmaster


async def test_rospy_talker_to_our_subscriber(rosmaster, ros_home) -> None:
    async with Node("/our_listener", rosmaster) as node:
        sub = await node.subscribe("/chatter_py", "std_msgs/String")
        async with process(SYS_PY, str(NODES / "talker.py"), "/chatter_py", "200", env=ros_env(rosmaster, ros_home)) as proc:
            got = [(await sub.get(30)).data for _ in range(200)]
            await read_until(proc, "SENT 200", 10, [])
        assert got == [f"msg {i}" for i in range(200)]
        (header,) = sub.connection_headers
        assert header["md5sum"] == STRING_MD5 and header["type"] == "std_msgs/String"
        assert header["callerid"] == "/rospy_talker"


async def test_our_publisher_to_rospy_listener(rosmaster, ros_home) -> None:
    async with Node("/our_talker", rosmaster) as node:
        pub = await node.advertise("/chatter_to_py", "std_msgs/String")
        async with process(SYS_PY, str(NODES / "listener.py"), "/chatter_to_py", "100", env=ros_env(rosmaster, ros_home)) as proc:
            seen: list[str] = []
            await read_until(proc, "READY", 20, seen)
            await pub.wait_for_subscribers(1, 20)
            for i in range(100):
                pub.publish(node.msg("std_msgs/String", data=f"hello {i}"))
            await read_until(proc, "DONE", 20, seen)
        got = [line.split()[1:] for line in seen if line.startswith("GOT")]
        assert got == [[f"{i}", STRING_MD5] for i in range(100)] or [g for g in got] == [
            ["hello", str(i), STRING_MD5] for i in range(100)
        ]


async def test_our_publisher_to_rostopic_echo(rosmaster, ros_home) -> None:
    rostopic = require("rostopic")["rostopic"]
    async with Node("/our_echo_talker", rosmaster) as node:
        pub = await node.advertise("/echo_me", "std_msgs/String", latch=True)
        pub.publish(node.msg("std_msgs/String", data="latched 0"))

        async def keep_publishing() -> None:
            i = 1
            while True:
                await asyncio.sleep(0.05)
                pub.publish(node.msg("std_msgs/String", data=f"latched {i}"))
                i += 1

        task = asyncio.create_task(keep_publishing())
        try:
            out = await sh(rostopic, "echo", "-n", "3", "/echo_me", env=ros_env(rosmaster, ros_home))
        finally:
            task.cancel()
        values = re.findall(r'data: "latched (\d+)"', out)
        assert len(values) == 3, out
        first = int(values[0])  # the latched (latest) message, then the next ones in order
        assert [int(v) for v in values] == [first, first + 1, first + 2]


async def test_roscpp_talker_to_our_subscriber(rosmaster, ros_home, roscpp_talker) -> None:
    async with Node("/our_cpp_listener", rosmaster) as node:
        sub = await node.subscribe("/chatter_cpp", "std_msgs/String")
        env = ros_env(rosmaster, ros_home)
        async with process(roscpp_talker, "/chatter_cpp", "300", env=env) as proc:
            got = [(await sub.get(30)).data for _ in range(300)]
            await read_until(proc, "SENT 300", 10, [])
        assert got == [f"msg {i}" for i in range(300)]
        (header,) = sub.connection_headers
        assert header["md5sum"] == STRING_MD5 and header["callerid"] == "/roscpp_talker"


async def test_rospy_service_called_by_our_client(rosmaster, ros_home) -> None:
    async with Node("/our_client", rosmaster) as node:
        async with process(SYS_PY, str(NODES / "services.py"), "serve", env=ros_env(rosmaster, ros_home)) as proc:
            await read_until(proc, "READY", 20, [])
            req = msgs.msg_class("roscpp/GetLoggers_Request")()
            for _ in range(2):
                resp = await node.call_service("/rospy_loggers", "roscpp/GetLoggers", req)
                assert [(lg.name, lg.level) for lg in resp.loggers] == [("rospy.server", "debug"), ("x", "warn")]
            # every rospy node also serves ~get_loggers: a second real server
            resp = await node.call_service("/rospy_server/get_loggers", "roscpp/GetLoggers", req)
            assert any(lg.name.startswith("rospy") for lg in resp.loggers)


async def test_our_service_called_by_rospy(rosmaster, ros_home) -> None:
    async with Node("/our_server", rosmaster) as node:
        Logger = msgs.msg_class("roscpp/Logger")
        Resp = msgs.msg_class("roscpp/GetLoggers_Response")
        calls = []

        async def handle(req):
            calls.append(req)
            return Resp(loggers=[Logger(name="cryptoros", level="info"), Logger(name="n2", level="error")])

        await node.advertise_service("/our_loggers", "roscpp/GetLoggers", handle)
        env = ros_env(rosmaster, ros_home)
        async with process(SYS_PY, str(NODES / "services.py"), "call", "/our_loggers", env=env) as proc:
            seen: list[str] = []
            await read_until(proc, "LOGGERS", 20, seen)
            await read_until(proc, "LOGGERS", 10, seen)
        assert [s.strip() for s in seen if s.startswith("LOGGERS")] == ["LOGGERS cryptoros=info,n2=error"] * 2
        assert len(calls) == 2


# ----------------------------------------------------------------- real ROS against our embedded master


async def test_rospy_and_ros_tools_against_our_master(our_master, ros_home) -> None:
    tools = require("rostopic", "rosnode")
    env = ros_env(our_master, ros_home)
    async with process(SYS_PY, str(NODES / "listener.py"), "/via_ours", "50", env=env) as listener:
        seen: list[str] = []
        await read_until(listener, "READY", 20, seen)
        async with process(SYS_PY, str(NODES / "talker.py"), "/via_ours", "50", "1", "30", env=env) as talker:
            await read_until(listener, "DONE 50", 30, seen)
            await read_until(talker, "SENT 50", 10, [])
            got = [line.split()[2] for line in seen if line.startswith("GOT")]
            assert got == [str(i) for i in range(50)]

            topics = await sh(tools["rostopic"], "list", env=env)
            assert "/via_ours" in topics.split() and "/rosout" in topics.split()
            info = await sh(tools["rostopic"], "info", "/via_ours", env=env)
            assert "Type: std_msgs/String" in info and "/rospy_talker" in info and "/rospy_listener" in info
            nodes = await sh(tools["rosnode"], "list", env=env)
            assert {"/rospy_talker", "/rospy_listener"} <= set(nodes.split())
            ninfo = await sh(tools["rosnode"], "info", "/rospy_listener", env=env)
            assert "/via_ours" in ninfo and "Pid:" in ninfo


async def test_rostopic_pub_and_echo_through_our_master_with_our_node(our_master, ros_home) -> None:
    tools = require("rostopic")
    env = ros_env(our_master, ros_home)
    async with Node("/our_sub_tools", our_master) as node:
        sub = await node.subscribe("/from_rostopic", "std_msgs/String")
        await sh(tools["rostopic"], "pub", "-1", "/from_rostopic", "std_msgs/String", "data: from the cli", env=env, timeout=30)
        msg = await sub.get(10)
        assert msg.data == "from the cli"

        pub = await node.advertise("/to_rostopic", "std_msgs/String", latch=True)
        pub.publish(node.msg("std_msgs/String", data="hello echo"))
        out = await sh(tools["rostopic"], "echo", "-n", "1", "/to_rostopic", env=env)
        assert 'data: "hello echo"' in out
        typ = await sh(tools["rostopic"], "type", "/to_rostopic", env=env)
        assert typ.strip() == "std_msgs/String"
