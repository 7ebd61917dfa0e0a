"""A live ROS 1 topic stream between two robots of the lab network, for the tests that
cut it or stop the interceptors under it (no tests here)."""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Iterator

from tests.interceptor_harness import NODE, SYS_PY, got, read_lines, wait_registered
from tests.support import running


@contextlib.contextmanager
def talker_a_to_listener_b(net) -> Iterator[subprocess.Popen]:
    """Robot A's rospy talker (20 Hz) and robot B's rospy listener, messages arriving:
    yields the listener's process (its GOT lines)."""
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "1000000", "20", "300"],
                 env=net.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(net, "/talker_a")
        with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "300"], env=net.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            assert got(read_lines(sub, "GOT", 20))
            yield sub

