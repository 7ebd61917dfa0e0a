"""A node name released by its owner stays its owner's for a while (master role)."""

from __future__ import annotations

from interceptor.name_holds import NameHolds
from tests.support import Clock


def test_a_released_name_is_held_for_its_owner_until_the_hold_ends():
    clock = Clock()
    holds = NameHolds(8, clock=clock)
    holds.release("/r0_base", "robot0", 120.0)
    assert holds.holder("/r0_base") == "robot0" and holds.holder("/other") is None
    clock.t += 119.9
    assert holds.holder("/r0_base") == "robot0"
    clock.t += 0.2
    assert holds.holder("/r0_base") is None and len(holds) == 0  # over: free for anyone


def test_registering_again_ends_the_hold_and_zero_seconds_holds_nothing():
    clock = Clock()
    holds = NameHolds(8, clock=clock)
    holds.release("/r0_base", "robot0", 120.0)
    holds.claim("/r0_base")  # the owner registered it again (the owners table has it)
    assert holds.holder("/r0_base") is None and len(holds) == 0
    holds.release("/r0_base", "robot0", 0.0)
    assert holds.holder("/r0_base") is None and len(holds) == 0


def test_one_manager_churning_names_keeps_at_most_its_bound_and_never_pushes_out_anothers():
    clock = Clock()
    holds = NameHolds(4, clock=clock)
    holds.release("/r0_base", "robot0", 120.0)
    for i in range(1000):  # a manager with a pattern grant registering and dropping names in a loop
        holds.release(f"/rostopic_{i}", "tools", 120.0)
        clock.t += 0.01
    assert holds.holder("/r0_base") == "robot0"  # robot0's hold is its own
    assert len(holds) == 1 + 4  # the churner's newest four
    assert holds.holder("/rostopic_999") == "tools" and holds.holder("/rostopic_995") is None


def test_expired_holds_of_a_manager_go_when_it_releases_another():
    clock = Clock()
    holds = NameHolds(100, clock=clock)
    for i in range(10):
        holds.release(f"/n{i}", "m", 5.0)
    clock.t += 10
    holds.release("/last", "m", 5.0)
    assert len(holds) == 1 and holds.holder("/last") == "m"
