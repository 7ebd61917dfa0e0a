"""A peer's open streams are capped (``[limits] max_connections_per_peer``) from its very
first burst: the count is taken before the interceptor's first token for that peer is
fetched, not after (insider audit: streams admitted while that fetch was under way each
saw the count without the others, and all were let in).

Real rosmaster, rospy talker, interceptors on separate network-namespace hosts, and a
rogue speaking to robot A's public port by hand with robot B's valid certificate and token.
"""

from __future__ import annotations

import contextlib

import pytest

from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    master_state,
    nodes_in_state,
    robot_network,
    rogue_preamble,
    rogue_reply,
    rogue_to,
    rogue_xmlrpc,
    separate_hosts,
    token_of,
)
from tests.support import running, until

pytestmark = [pytest.mark.ros1]

CAP = 2


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    extra = {"robot_a": f"[limits]\nmax_connections_per_peer = {CAP}\n"}
    with robot_network(tmp_path_factory.mktemp("cap"), start=("master", "robot_a", "robot_b"), extra=extra,
                       netns=separate_hosts()) as net:
        yield net


def test_a_first_burst_of_a_peers_streams_is_held_to_its_cap(network):
    token = token_of(network, "robot_b")
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"],
                 env=network.ros_env("robot_a")):
        until(lambda: "/talker_a" in nodes_in_state(master_state(network)), 20, "the talker registered")
        with rogue_to(network, "master", "robot_b") as s:
            assert rogue_preamble(s, token, "master").ok
            node_api = rogue_xmlrpc(s, "lookupNode", "/rogue", "/talker_a").value[2]
        target = node_api.rsplit("/", 1)[1]
        with contextlib.ExitStack() as held:
            socks = [held.enter_context(rogue_to(network, "robot_a", "robot_b")) for _ in range(3 * CAP)]
            from cryptoros.tunnel import Preamble, encode

            for s in socks:  # every preamble before robot A has fetched its first token for robot B
                s.sendall(encode(Preamble(token=token, purpose="node", target=target)))
            replies = []
            for s in socks:
                s.settimeout(15)
                try:
                    replies.append(rogue_reply(s))
                except OSError:  # refused streams may be reset
                    replies.append(None)
    admitted = sum(1 for r in replies if r is not None and r.ok)
    assert admitted == CAP, f"{admitted} of {len(socks)} streams admitted, cap {CAP}"
    assert "connection_limit" in network.hosts["robot_a"].logs()

