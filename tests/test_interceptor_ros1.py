"""The interceptor with real, unmodified ROS 1 nodes (Debian rospy, rostopic, rosnode).

Three hosts on loopback (master 127.0.0.4, robot A 127.0.0.2, robot B 127.0.0.3), a
real rosmaster behind the master's interceptor, a real cryptoros-authz daemon.
"""

from __future__ import annotations

import subprocess
import time

import pytest

from tests.interceptor_harness import NODES, SYS_PY, robot_network
from tests.support import running

pytestmark = [pytest.mark.ros1]


def wait_line(proc: subprocess.Popen, needle: str, timeout: float) -> list[str]:
    """Read a process's output until a line contains ``needle`` (bounded)."""
    import selectors

    seen: list[str] = []
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not sel.select(timeout=max(0.0, deadline - time.monotonic())):
            break
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line)
        if needle in line:
            return seen
    raise AssertionError(f"no {needle!r} within {timeout}s; output:\n{''.join(seen)}")


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    with robot_network(tmp_path_factory.mktemp("net")) as net:
        yield net


def test_talker_on_a_reaches_listener_on_b(network):
    with running([SYS_PY, str(NODES / "listener.py"), "/chatter", "10"], env=network.ros_env("robot_b")) as listener:
        wait_line(listener, "READY", 20)
        with running([SYS_PY, str(NODES / "talker.py"), "/chatter", "10"], env=network.ros_env("robot_a")) as talker:
            lines = wait_line(listener, "DONE", 40)
            wait_line(talker, "SENT 10", 10)
    got = [l.split()[1] + " " + l.split()[2] for l in lines if l.startswith("GOT")]
    assert got == [f"msg {i}" for i in range(10)], "".join(lines) + network.hosts["robot_a"].logs()[-3000:]
