"""The node role's memory of topic streams a peer's side refused, and when their
subscribers are told the publishers again (:mod:`interceptor.ros1.refusals`)."""

from __future__ import annotations

import pytest

from interceptor.ros1.refusals import MAX_REFUSED, REFUSED_MEMORY, REFUSED_RECHECK, RefusedStreams
from tests.support import Clock


def test_a_grant_given_back_tells_the_subscribers_once_rospys_own_check_is_over():
    clock = Clock()
    refused = RefusedStreams(clock)
    refused.refused("robot_a", "/chatter")
    clock.t += 0.2  # robot A's next token (its grant back) arrives
    assert refused.due("robot_a") == [("/chatter", pytest.approx(REFUSED_RECHECK - 0.2))]
    assert refused.due("robot_a") == []  # told once; nothing until refused again
    assert refused.due("robot_b") == []


def test_streams_refused_again_and_again_are_told_again_ever_later_until_one_is_accepted():
    """Security audit (MEDIUM): an insider's side refusing every stream while it showed
    token after token had each topic's subscribers told again every 1.5 s."""
    clock = Clock()
    refused = RefusedStreams(clock)
    waits = []
    for _ in range(8):
        refused.refused("mallory", "/scan")
        clock.t += 0.01
        ((topic, wait),) = refused.due("mallory")
        waits.append(round(wait + 0.01, 6))
        clock.t += wait  # told; the subscriber connects again and is refused again
    assert waits == [1.5, 3.0, 6.0, 12.0, 24.0, 48.0, REFUSED_MEMORY, REFUSED_MEMORY]
    refused.accepted("mallory", "/scan")  # a stream went through: the back-off starts over
    refused.refused("mallory", "/scan")
    assert refused.due("mallory") == [("/scan", REFUSED_RECHECK)]
    # another manager's refusals of the same topic have their own back-off
    refused.refused("robot_a", "/scan")
    assert refused.due("robot_a") == [("/scan", REFUSED_RECHECK)]


def test_an_old_refusal_is_not_acted_on_and_the_memory_is_bounded():
    clock = Clock()
    refused = RefusedStreams(clock)
    refused.refused("robot_a", "/old")
    clock.t += REFUSED_MEMORY
    assert refused.due("robot_a") == []
    for m in range(MAX_REFUSED + 10):
        for t in range(3):
            refused.refused(f"m{m}", f"/t{t}")
    for t in range(MAX_REFUSED + 10):
        refused.refused("busy", f"/t{t}")
    assert refused.due("m0") == []  # the oldest managers forgotten
    assert len(refused.due(f"m{MAX_REFUSED + 9}")) == 3
    assert len(refused.due("busy")) == MAX_REFUSED


def test_tellings_after_a_managers_streams_end_are_paced_per_manager_after_a_burst():
    """Re-audit (MEDIUM): an insider's node that accepted each subscriber's stream and
    closed it at once (nothing refused, so no back-off) had the victim's subscribers
    told again 330 times in 15 s over 30 topics. Every telling now takes a turn in its
    manager's bucket: a burst covers a robot's topics all cut at once, then
    TELLINGS_PER_SECOND; another manager's turns are its own."""
    from interceptor.ros1.refusals import TELLING_BURST, TELLINGS_PER_SECOND

    clock = Clock()
    refused = RefusedStreams(clock)
    assert [refused.paced("mallory") for _ in range(TELLING_BURST)] == [0.0] * TELLING_BURST
    waits = [refused.paced("mallory") for _ in range(4)]  # queued one behind the other
    assert waits == pytest.approx([n / TELLINGS_PER_SECOND for n in range(1, 5)])
    assert refused.paced("robot_a") == 0.0
    clock.t += 60  # the bucket fills again
    assert refused.paced("mallory") == 0.0
