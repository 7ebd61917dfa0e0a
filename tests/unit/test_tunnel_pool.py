"""The XML-RPC tunnel pool under a burst: a few tunnels shared, none waiting for long."""

from __future__ import annotations

import asyncio

import pytest

from interceptor.ros1 import TunnelPool


class FakeTunnel:
    made: list[FakeTunnel] = []

    def __init__(self, *args) -> None:
        self.calls = 0
        self.closed = False
        FakeTunnel.made.append(self)

    async def call(self, request):
        self.calls += 1
        await asyncio.sleep(request)  # the "request" is how long the far end takes
        if request < 0:
            raise ConnectionResetError("tunnel closed")
        return "ok"

    async def close(self) -> None:
        self.closed = True

    def close_now(self) -> None:
        self.closed = True


@pytest.fixture(autouse=True)
def fake_tunnels():
    FakeTunnel.made = []


async def test_a_burst_of_calls_shares_max_busy_tunnels():
    pool = TunnelPool(FakeTunnel, max_idle=4, max_busy=3)
    results = await asyncio.gather(*(pool.call(0.01) for _ in range(20)))
    assert results == ["ok"] * 20
    assert len(FakeTunnel.made) == 3  # not one handshake per call
    assert sum(t.calls for t in FakeTunnel.made) == 20


async def test_a_call_waits_at_most_pool_wait_for_a_busy_tunnel():
    pool = TunnelPool(FakeTunnel, max_idle=4, max_busy=2, wait=0.05)
    slow = [asyncio.ensure_future(pool.call(1.0)) for _ in range(2)]
    await asyncio.sleep(0)
    started = asyncio.get_running_loop().time()
    assert await pool.call(0.0) == "ok"
    assert asyncio.get_running_loop().time() - started < 0.5  # opened its own after POOL_WAIT
    assert len(FakeTunnel.made) == 3
    for task in slow:
        task.cancel()


async def test_a_failed_call_closes_its_tunnel_and_lets_a_waiter_open_one():
    pool = TunnelPool(FakeTunnel, max_idle=4, max_busy=1)
    failing = asyncio.ensure_future(pool.call(-0.01))
    await asyncio.sleep(0)
    waiting = asyncio.ensure_future(pool.call(0.0))
    with pytest.raises(ConnectionResetError):
        await failing
    assert await waiting == "ok"
    assert FakeTunnel.made[0].closed
    assert len(FakeTunnel.made) == 2


async def _until(condition, timeout: float = 5.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not condition():
        assert asyncio.get_running_loop().time() < deadline, "not within the bound"
        await asyncio.sleep(0.01)


async def test_an_idle_tunnel_is_closed_after_the_idle_timeout_and_a_used_one_is_kept():
    pool = TunnelPool(FakeTunnel, max_idle=4, max_busy=2, idle_timeout=0.2)
    await asyncio.gather(pool.call(0.0), pool.call(0.0))
    old, recent = FakeTunnel.made
    assert pool.idle_count == 2 and not old.closed
    await _until(lambda: pool.idle_count == 0)
    assert old.closed and recent.closed
    assert await pool.call(0.0) == "ok"  # the next call opens a fresh tunnel
    assert len(FakeTunnel.made) == 3 and pool.idle_count == 1


async def test_a_closed_pool_keeps_no_tunnel_even_one_coming_back_from_a_call():
    pool = TunnelPool(FakeTunnel, max_idle=4, max_busy=2, idle_timeout=60.0)
    await asyncio.gather(pool.call(0.0), pool.call(0.0))
    idle, taken = FakeTunnel.made
    under_way = asyncio.ensure_future(pool.call(0.05))  # takes the most recently used
    await asyncio.sleep(0)
    pool.close()
    assert idle.closed and not taken.closed and pool.idle_count == 0
    assert await under_way == "ok"
    assert all(t.closed for t in FakeTunnel.made) and pool.idle_count == 0
    assert await pool.call(0.0) == "ok"  # still answers (a connection holding it), keeps nothing
    assert all(t.closed for t in FakeTunnel.made) and pool.idle_count == 0
