"""cryptoros.ratelimit: per-key budgets on a clock passed in."""

from __future__ import annotations

from cryptoros.ratelimit import Shunned, TokenBuckets


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_token_buckets_allow_a_burst_then_the_rate():
    clock = Clock()
    buckets = TokenBuckets(rate=2, burst=3, clock=clock)
    assert [buckets.allow("a") for _ in range(4)] == [True, True, True, False]
    assert buckets.allow("b")  # a key of its own
    clock.now += 0.5
    assert buckets.allow("a") and not buckets.allow("a")


def test_a_key_is_shunned_past_its_failure_budget_for_its_time_and_then_forgiven():
    clock = Clock()
    shun = Shunned(rate=1, burst=3, seconds=10, clock=clock)
    assert [shun.failed("stranger") for _ in range(4)] == [False, False, False, True]
    assert shun.left("stranger") == 10 and shun.left("robot") == 0
    clock.now += 4
    assert shun.left("stranger") == 6
    clock.now += 6
    assert shun.left("stranger") == 0
    assert not shun.failed("stranger")  # 10 s refilled its budget


def test_shunned_keys_are_bounded():
    clock = Clock()
    shun = Shunned(rate=0.001, burst=1, seconds=60, max_keys=100, clock=clock)
    for i in range(1000):
        shun.failed(i)
        shun.failed(i)
    assert len(shun._until) == 100 and shun.left(999) > 0 and shun.left(0) == 0
