"""A robot's bring-up through the interceptors: dozens of subscriber nodes on robot B
start at once against one latched publisher on robot A, and every one receives its
message. Robot B's interceptor opens at most ``max_pending_per_certificate`` streams to
one peer endpoint at a time (the peer refuses more unauthenticated streams from one
certificate with ``pending_limit``), so the burst waits its turn instead of being
refused: before, 7 of 50 subscribers of ``cryptoros bench interceptor``'s bring-up
row failed to register."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import urllib.request

import pytest

from cryptoros.ros1.node import Node
from cryptoros.ros1.rpc import RosApiError, call
from tests.authz_support import ok
from tests.interceptor_harness import STRING, denials, robot_network
from tests.support import until

pytestmark = [pytest.mark.ros1]

SUBSCRIBERS = 30  # more than the 8 pending streams per certificate and 16 per source a peer admits


@pytest.mark.timeout(120)
def test_subscribers_starting_at_once_all_receive_and_none_is_refused(tmp_path):
    with robot_network(tmp_path) as net:

        async def bring_up() -> list[str]:
            async with Node("/talker_a", net.hosts["robot_a"].master_uri) as talker:
                pub = await talker.advertise("/chatter", STRING, latch=True)
                pub.publish(talker.msg(STRING, data="bring-up"))
                received: dict[int, str] = {}
                nodes = [Node(f"/burst_{i}", net.hosts["robot_b"].master_uri) for i in range(SUBSCRIBERS)]

                async def one(i: int) -> None:
                    got = asyncio.Event()

                    def on_msg(msg, i=i) -> None:
                        received[i] = msg.data
                        got.set()

                    await nodes[i].start()
                    await nodes[i].subscribe("/chatter", STRING, on_msg)
                    await got.wait()

                try:
                    outcomes = await asyncio.gather(*(asyncio.wait_for(one(i), 30) for i in range(SUBSCRIBERS)),
                                                    return_exceptions=True)
                finally:
                    await asyncio.gather(*(n.close() for n in nodes), return_exceptions=True)
                errors = [repr(o) for o in outcomes if isinstance(o, BaseException)]
                assert not errors, errors[:3]
                return [received[i] for i in range(SUBSCRIBERS)]

        assert asyncio.run(bring_up()) == ["bring-up"] * SUBSCRIBERS
        for host in ("robot_a", "master"):
            assert "pending_limit" not in denials(net, host), denials(net, host)[-2000:]


def _status(net) -> dict:
    with net.inside("robot_b"):
        url = f"http://127.0.0.1:{net.hosts['robot_b'].metrics_port}/status"
        with urllib.request.urlopen(url, timeout=5) as reply:
            return json.loads(reply.read())


def _shared(net) -> int:
    return _status(net)["ros1"]["topic_answers_shared"]


@pytest.mark.timeout(120)
def test_subscribers_registered_here_share_the_publishers_answer_and_other_callers_ask_the_far_side(tmp_path):
    """requestTopic: the subscribers robot B registered share one tunnelled answer per
    publisher and topic (interceptor/ros1/answers.py); a process that registered
    nothing through B gets robot A's own decision, a refusal included."""
    with robot_network(tmp_path) as net:
        master_b = net.hosts["robot_b"].master_uri

        async def bring_up() -> None:
            async with Node("/talker_a", net.hosts["robot_a"].master_uri) as talker:
                pub = await talker.advertise("/chatter", STRING, latch=True)
                pub.publish(talker.msg(STRING, data="bring-up"))
                nodes = [Node(f"/burst_{i}", master_b) for i in range(SUBSCRIBERS)]

                async def one(node: Node) -> None:
                    got = asyncio.Event()
                    await node.start()
                    await node.subscribe("/chatter", STRING, lambda _msg: got.set())
                    await got.wait()

                try:
                    await asyncio.gather(*(asyncio.wait_for(one(n), 30) for n in nodes))
                    # robot A's talker as B's nodes are handed it: a relay of robot B
                    relay = await call(master_b, "lookupNode", "/probe", "/talker_a")
                    # the burst asked robot A once (again each time it outlasted an answer's 2 s)
                    assert _shared(net) >= SUBSCRIBERS // 2
                    before = _shared(net)
                    answer = await call(relay, "requestTopic", "/unregistered", "/chatter", [["TCPROS"]])
                    assert answer[0] == "TCPROS"  # robot A's answer (its grant: any node of B)
                    with pytest.raises(RosApiError, match="denied by cryptoros"):  # robot A refuses /secret
                        await call(relay, "requestTopic", "/unregistered", "/secret", [["TCPROS"]])
                    assert _shared(net) == before
                    await answers_end_with_the_grant(relay)
                finally:
                    await asyncio.gather(*(n.close() for n in nodes), return_exceptions=True)

        async def answers_end_with_the_grant(relay: str) -> None:
            """Once robot B's token lost the grant that covered its subscribers, B shares no
            answer with them, not even one kept less than 2 s: robot A decides (and refuses,
            once the revocation reached it too)."""
            async def fresh_answer() -> None:  # a call that shared nothing asked robot A: kept from now
                for _ in range(50):
                    counted = _shared(net)
                    await call(relay, "requestTopic", "/burst_0", "/chatter", [["TCPROS"]])
                    if _shared(net) == counted:
                        return
                    await asyncio.sleep(0.1)
                raise AssertionError("every requestTopic was shared for 5 s")

            granted = ["*", "subscribe", "/chatter", STRING]
            assert granted in _status(net)["token"]["grants"]
            await fresh_answer()
            kept_at = time.monotonic()
            ok(net.cli("revoke", "robot_b", "subscribe", "*", "/chatter"))
            def without_grant() -> bool:  # (no token at all for a moment: the revoked one replaced)
                token = _status(net)["token"]
                return token is not None and granted not in token["grants"]

            until(without_grant, 30, "robot B's token without the grant")
            left = time.monotonic() - kept_at
            before = _shared(net)
            with contextlib.suppress(RosApiError):  # robot A decides: a refusal once the revocation reached it
                await call(relay, "requestTopic", "/burst_1", "/chatter", [["TCPROS"]])
            assert _shared(net) == before, f"robot B shared an answer kept {time.monotonic() - kept_at:.1f} s"
            print(f"the grant left robot B's token {left:.2f} s after the answer was kept")

        asyncio.run(bring_up())
