"""rosmaster's notifications queued per node API (interceptor/ros1/notices.py): answered
at once, one call in flight per API, the latest per topic or key, bounded."""

from __future__ import annotations

import asyncio

from cryptoros.ros1.xmlrpc import Request
from interceptor.ros1.notices import QUEUED, Notices


def update(method: str, name: str, value) -> Request:
    return Request(method=method, params=("/master", name, value))


def test_a_stuck_api_holds_only_its_own_queue_and_gets_the_latest_of_each_key():
    async def scenario() -> None:
        release = asyncio.Event()
        calls: list[tuple[str, tuple]] = []

        async def deliver(target, request) -> None:
            calls.append((target, request.params))
            if target == "stuck":
                await release.wait()

        notices = Notices(deliver, asyncio.ensure_future)
        assert notices.post("stuck", update("paramUpdate", "/a/b", 1)) is QUEUED
        await asyncio.sleep(0)  # the first call is in flight, and never answers
        for value in (2, 3):
            notices.post("stuck", update("paramUpdate", "/a/b", value))
        notices.post("stuck", update("paramUpdate", "/a", {"b": 4}))
        notices.post("stuck", update("paramUpdate", "/a/b", 5))  # after /a now: delivered after it
        notices.post("stuck", update("publisherUpdate", "/chatter", ["http://x:1/"]))
        notices.post("other", update("publisherUpdate", "/chatter", ["http://y:2/"]))
        for _ in range(5):
            await asyncio.sleep(0)
        assert ("other", ("/master", "/chatter", ["http://y:2/"])) in calls  # not behind the stuck one
        assert [c for c in calls if c[0] == "stuck"] == [("stuck", ("/master", "/a/b", 1))]  # one in flight
        release.set()
        for _ in range(10):
            await asyncio.sleep(0)
        assert [c[1] for c in calls if c[0] == "stuck"] == [
            ("/master", "/a/b", 1), ("/master", "/a", {"b": 4}), ("/master", "/a/b", 5),
            ("/master", "/chatter", ["http://x:1/"])]
        assert (notices.replaced, notices.delivered, notices.pending()) == (2, 5, 0)

    asyncio.run(scenario())


def test_the_queue_of_one_api_is_bounded_and_a_failed_call_does_not_stop_it():
    async def scenario() -> None:
        gate = asyncio.Event()
        seen: list[str] = []

        async def deliver(target, request) -> None:
            await gate.wait()
            seen.append(request.params[1])
            if request.params[1] == "/k3":
                raise ConnectionResetError("gone")

        notices = Notices(deliver, asyncio.ensure_future, max_queued=3)
        for i in range(6):
            notices.post("api", update("paramUpdate", f"/k{i}", i))
        await asyncio.sleep(0)
        assert notices.pending() <= 3 and notices.dropped >= 2
        gate.set()
        for _ in range(10):
            await asyncio.sleep(0)
        assert seen[-3:] == ["/k3", "/k4", "/k5"] and notices.pending() == 0

    asyncio.run(scenario())
