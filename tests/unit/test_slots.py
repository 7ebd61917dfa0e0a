"""KeyedSlots: at most N holders per key, waiters in line, a bounded wait, no entry kept
for a key nobody uses."""

import asyncio

import pytest

from cryptoros.errors import PolicyDenied
from interceptor.slots import KeyedSlots


def busy() -> PolicyDenied:
    return PolicyDenied("rate_limited", "busy")


def test_a_key_has_at_most_its_limit_of_holders_and_others_keys_are_not_held_up():
    async def main():
        slots, inside, most = KeyedSlots(), {"a": 0, "b": 0}, {"a": 0, "b": 0}
        gate = asyncio.Event()

        async def user(key):
            async with slots.hold(key, 2, 5.0, busy):
                inside[key] += 1
                most[key] = max(most[key], inside[key])
                await gate.wait()
                inside[key] -= 1

        tasks = [asyncio.create_task(user("a")) for _ in range(5)] + [asyncio.create_task(user("b"))]
        await asyncio.sleep(0.01)
        assert inside == {"a": 2, "b": 1}  # three of a's wait; b's one is not behind them
        gate.set()
        await asyncio.gather(*tasks)
        assert most == {"a": 2, "b": 1} and len(slots) == 0  # no entry left behind

    asyncio.run(main())


def test_a_wait_past_its_bound_raises_the_callers_error_and_frees_its_place():
    async def main():
        slots = KeyedSlots()
        release = asyncio.Event()

        async def holder():
            async with slots.hold("peer", 1, 5.0, busy):
                await release.wait()

        task = asyncio.create_task(holder())
        await asyncio.sleep(0.01)
        with pytest.raises(PolicyDenied, match="rate_limited"):
            async with slots.hold("peer", 1, 0.05, busy):
                pass
        assert len(slots) == 1  # the holder's entry only
        release.set()
        await task
        assert len(slots) == 0
        async with slots.hold("peer", 1, 0.05, busy):  # free again
            pass

    asyncio.run(main())
