"""A publisher's requestTopic answer shared by subscribers starting at once
(interceptor/ros1/answers.py): one call for many, kept for a bounded time, never a
refusal or a failure shared."""

from __future__ import annotations

import asyncio

import pytest

from cryptoros.ros1.xmlrpc import Fault, Response
from interceptor.ros1.answers import TopicAnswers

READY = Response(value=[1, "ready", ["TCPROS", "10.0.0.2", 7000]])
REFUSED = Response(value=[-1, "denied by cryptoros: not_granted", 0])


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Far:
    """The far side: counts calls, answers when released."""

    def __init__(self, answer: Response | Fault | Exception) -> None:
        self.answer = answer
        self.calls = 0
        self.release = asyncio.Event()

    async def __call__(self) -> Response | Fault:
        self.calls += 1
        await self.release.wait()
        if isinstance(self.answer, Exception):
            raise self.answer
        return self.answer


async def test_fifty_subscribers_asking_at_once_make_one_call_and_all_get_its_answer():
    answers, far = TopicAnswers(clock=Clock()), Far(READY)
    asks = [asyncio.ensure_future(answers.ask(("api1", "/scan"), far)) for _ in range(50)]
    await asyncio.sleep(0)
    far.release.set()
    assert await asyncio.gather(*asks) == [READY] * 50
    assert far.calls == 1 and answers.shared == 49


async def test_an_answer_serves_later_askers_for_its_seconds_then_the_far_side_is_asked_again():
    clock = Clock()
    answers, far = TopicAnswers(seconds=2.0, clock=clock), Far(READY)
    far.release.set()
    assert await answers.ask("k", far) is READY
    clock.now += 1.9
    assert await answers.ask("k", far) is READY and far.calls == 1
    clock.now += 0.2
    assert await answers.ask("k", far) is READY and far.calls == 2
    other = Far(READY)
    other.release.set()
    await answers.ask("other topic", other)
    assert other.calls == 1  # each key its own


async def test_a_refusal_is_never_shared_each_waiter_asks_for_itself():
    answers, far = TopicAnswers(clock=Clock()), Far(REFUSED)
    asks = [asyncio.ensure_future(answers.ask("k", far)) for _ in range(3)]
    await asyncio.sleep(0)
    far.release.set()
    assert await asyncio.gather(*asks) == [REFUSED] * 3
    assert far.calls == 3 and answers.shared == 0
    await answers.ask("k", far)
    assert far.calls == 4  # not kept either


async def test_a_failed_call_raises_to_its_caller_and_the_waiters_ask_for_themselves():
    answers, far = TopicAnswers(clock=Clock()), Far(ConnectionError("tunnel closed"))
    first = asyncio.ensure_future(answers.ask("k", far))
    await asyncio.sleep(0)
    waiter_far = Far(READY)
    waiter_far.release.set()
    waiter = asyncio.ensure_future(answers.ask("k", waiter_far))
    await asyncio.sleep(0)
    far.release.set()
    with pytest.raises(ConnectionError):
        await first
    assert await waiter is READY and waiter_far.calls == 1
    assert answers.shared == 0


async def test_kept_answers_are_bounded():
    answers = TopicAnswers(cap=3, clock=Clock())
    far = Far(READY)
    far.release.set()
    for i in range(10):
        await answers.ask(i, far)
    assert far.calls == 10
    await answers.ask(9, far)  # among the 3 kept
    assert far.calls == 10
    await answers.ask(0, far)  # long dropped
    assert far.calls == 11
