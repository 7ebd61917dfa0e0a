"""PartialFrames: one peer's unfinished frames across its streams, against one budget."""

import pytest

from cryptoros.errors import PolicyDenied
from interceptor.ros2_partial import PARTIAL_FRAMES_PER_PEER, PartialFrames


def test_a_peers_streams_share_one_budget_and_give_their_share_back():
    partial, size = PartialFrames(), 100
    limit = PARTIAL_FRAMES_PER_PEER * size
    with partial.charge("robot_a", size) as first, partial.charge("robot_a", size) as second:
        first(limit - 10)
        second(10)  # exactly the limit: allowed
        assert partial.held["robot_a"] == limit
        with partial.charge("robot_b", size) as other:
            other(limit)  # another peer's budget is its own
        with pytest.raises(PolicyDenied) as refused:
            second(11)
        assert refused.value.reason == "partial_frames"
        first(0)  # a frame finished: its bytes are given back at once
        second(11)
        assert partial.held["robot_a"] == 11
    assert partial.held == {}


def test_a_stream_cut_over_the_budget_gives_its_share_back():
    partial = PartialFrames()
    with partial.charge("robot_a", 100) as keep:
        keep(50)
        with pytest.raises(PolicyDenied), partial.charge("robot_a", 100) as over:
            over(PARTIAL_FRAMES_PER_PEER * 100)
        assert partial.held["robot_a"] == 50
