"""The interceptor's own access token (interceptor/authz_client.py TokenKeeper), driven
by a stand-in for the authorization server's ``POST /token``: when it is refreshed, and
that a token issued for another manager than the configured one is never held."""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import time

import pytest

import interceptor.authz_client as authz_client
from cryptoros.errors import TokenError
from interceptor.authz_client import OwnToken, TokenKeeper

WRONG = "the registry binds this certificate to manager 'robot_b', not 'robot_a'"


def token_for(subject: str, n: int) -> str:
    """A JWT-shaped token naming ``subject`` (the keeper reads its ``sub``; peers verify it)."""
    def part(obj: dict) -> str:
        return base64.urlsafe_b64encode(json.dumps(obj).encode()).rstrip(b"=").decode()
    return f"{part({'alg': 'RS256', 'typ': 'at+jwt'})}.{part({'sub': subject, 'jti': str(n)})}.c2ln"


class Authz:
    """``fetch_token`` as the server answers it: tokens for ``subjects`` in turn (the last
    one again and again), valid ``lifetime`` seconds."""

    def __init__(self, *subjects: str, lifetime: float = 300.0) -> None:
        self.subjects = list(subjects)
        self.lifetime = lifetime
        self.fetches = 0

    async def fetch_token(self, *, clock=time.time, resource: str | None = None) -> OwnToken:
        self.fetches += 1
        subject = self.subjects[min(self.fetches, len(self.subjects)) - 1]
        return OwnToken(token=token_for(subject, self.fetches), expires_at=clock() + self.lifetime)


@pytest.mark.parametrize(("lifetime", "margin", "delay"), [
    (300, 60, 150),   # half-way
    (600, 60, 300),
    (100, 60, 40),    # margin seconds before expiry, when that comes first
    (10, 8, 2),
    (30, 60, 15),     # a lifetime under the margin: half-way, not every second
    (60.5, 60, 30.25),
    (1.5, 60, 1.0),   # at least a second
    (0, 60, 1.0),
])
def test_a_token_is_refreshed_half_way_or_margin_seconds_before_expiry_and_never_every_second(lifetime, margin,
                                                                                           delay):
    assert authz_client.refresh_delay(lifetime, margin) == pytest.approx(delay)


async def test_a_token_shorter_lived_than_the_margin_is_not_fetched_every_second():
    authz = Authz("robot_a", lifetime=30)
    keeper = TokenKeeper(authz, refresh_margin=60)
    runner = asyncio.create_task(keeper.run())
    try:
        await asyncio.sleep(2.5)
    finally:
        runner.cancel()
    assert authz.fetches == 1  # the next one 15 s after it


async def test_a_token_for_another_manager_is_refused_and_none_is_held(caplog):
    keeper = TokenKeeper(Authz("robot_b"), refresh_margin=60, manager="robot_a")
    with caplog.at_level(logging.WARNING), pytest.raises(TokenError) as info:
        await keeper.refresh()
    assert (info.value.reason, info.value.detail) == ("wrong_manager", WRONG)
    with pytest.raises(TokenError) as info:
        keeper.current()  # health and status show this reason
    assert (info.value.reason, info.value.detail) == ("wrong_manager", WRONG)
    assert keeper.expires_at is None
    with pytest.raises(TokenError):
        await keeper.for_peer("x" * 43)  # nor is a token for a peer handed out
    errors = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(errors) == 1 and errors[0].levelno == logging.ERROR and WRONG in errors[0].getMessage(), errors


async def test_a_refresh_bringing_another_managers_token_drops_the_one_held_until_ours_comes_back():
    keeper = TokenKeeper(Authz("robot_a", "robot_b", "robot_a"), refresh_margin=60, manager="robot_a")
    await keeper.refresh()
    first = keeper.current()
    with pytest.raises(TokenError, match="wrong_manager"):
        await keeper.refresh()
    with pytest.raises(TokenError) as info:
        keeper.current()
    assert info.value.reason == "wrong_manager"  # not the earlier token: the registry no longer binds us to it
    await keeper.refresh()
    assert keeper.current() not in (first, None)


async def test_the_refresh_loop_logs_one_error_per_refused_token_and_no_warning(caplog):
    keeper = TokenKeeper(Authz("robot_b"), refresh_margin=60, manager="robot_a")
    with caplog.at_level(logging.INFO):
        runner = asyncio.create_task(keeper.run())
        try:
            await asyncio.sleep(0.3)  # one attempt; the next after a 1 s back-off
        finally:
            runner.cancel()
    lines = [(r.levelname, r.getMessage()) for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(lines) == 1 and lines[0][0] == "ERROR" and WRONG in lines[0][1], lines


async def test_failing_refreshes_are_shown_in_status_while_the_token_held_lasts():
    """Day-2 audit: with the authorization server's certificate expired every refresh
    failed, yet ``cryptoros status`` said ok until the fleet's tokens would run out."""
    from interceptor.status import render

    class Failing(Authz):
        async def fetch_token(self, *, clock=time.time, resource=None):
            if self.fetches >= 1:
                self.fetches += 1
                raise TokenError("authz_unreachable", "certificate has expired")
            return await super().fetch_token(clock=clock, resource=resource)

    keeper = TokenKeeper(Failing("robot_a"), refresh_margin=299.5, manager="robot_a")  # refresh at once
    runner = asyncio.create_task(keeper.run())
    try:
        await asyncio.wait_for(keeper.refreshed.wait(), 5)
        keeper.wake()
        for _ in range(50):
            if keeper.failing is not None:
                break
            await asyncio.sleep(0.05)
    finally:
        runner.cancel()
    assert keeper.failing is not None and keeper.failing[1] == "certificate has expired"
    assert keeper.current()  # the token held still serves
    status = {"manager": "robot_a", "roles": ["node"], "public": "127.0.0.1:1", "health": "ok",
              "token": None, "token_refresh": {"failing_for": 12, "reason": keeper.failing[1]},
              "certificate": {"serial": "1", "not_after": "2027-01-01T00:00:00", "days_left": 30},
              "feed": {"age": 1, "revoked_tokens": 0, "disabled_managers": []}, "open_streams": 0}
    assert "warning   token refresh failing for 12 s: certificate has expired" in render(status)


async def test_a_token_installed_by_a_reload_for_another_manager_is_refused_and_changes_nothing():
    keeper = TokenKeeper(Authz("robot_a"), refresh_margin=60, manager="robot_a")
    await keeper.refresh()
    held = keeper.current()
    wrong = await Authz("robot_b").fetch_token()
    with pytest.raises(TokenError, match="wrong_manager"):
        keeper.check(wrong)
    with pytest.raises(TokenError, match="wrong_manager"):
        keeper.install(wrong)
    assert keeper.current() == held


async def test_a_token_naming_no_manager_is_refused_too():
    keeper = TokenKeeper(Authz("robot_a"), refresh_margin=60, manager="robot_a")
    with pytest.raises(TokenError, match="wrong_manager"):
        keeper.install(OwnToken(token="not-a-jwt", expires_at=time.time() + 300))


async def test_without_a_configured_manager_no_subject_is_checked():
    keeper = TokenKeeper(Authz("robot_b"), refresh_margin=60)
    await keeper.refresh()
    assert keeper.current()


async def test_a_gateway_given_another_managers_token_reports_why_in_its_health(pki, tmp_path):
    """The running interceptor's keeper knows its manager: ``status`` (``cryptoros
    status``) shows the refusal, and no grants (the token is not held)."""
    from interceptor.config import parse
    from interceptor.gateway import Gateway

    own = pki.issue("robot_a", kind="interceptor", sans=("IP:127.0.0.1",))
    gateway = Gateway(parse({
        "manager": "robot_a",
        "tls": {"ca": str(pki.ca_cert), "cert": str(own.cert_path), "key": str(own.key_path)},
        "authz": {"url": "https://127.0.0.1:9"},  # never asked: the keeper's client is replaced
        "listen": {"public": "127.0.0.1:9", "local_master": "127.0.0.1:9"},
        "master": {"interceptor": "127.0.0.1:9"},
    }, base=tmp_path))
    gateway.keeper._client = Authz("robot_b")
    with pytest.raises(TokenError, match="wrong_manager"):
        await gateway.keeper.refresh()
    status = gateway.status()
    assert status["health"] == f"wrong_manager: {WRONG}" and status["token"] is None
    await gateway.authz.close()


def test_a_refresh_refused_forever_is_logged_at_first_then_once_a_minute_with_a_count():
    """A robot whose certificate was revoked asks again every second or so: the first
    failure is logged, then one line a minute with the count, and one when it works."""
    retries = authz_client.RetryLog(interval=60.0)
    start = time.mktime((2026, 11, 28, 21, 0, 0, 0, 0, -1))
    assert retries.succeeded() is None  # never failed: nothing to say
    assert retries.failed(start) == ""
    assert [retries.failed(start + s) for s in range(1, 60)] == [None] * 59
    assert retries.failed(start + 60) == "still refused: 61 tries since 21:00:00"
    assert retries.failed(start + 61) is None
    assert retries.succeeded() == "after 62 failed tries since 21:00:00"
    assert retries.succeeded() is None
    assert retries.failed(start + 200) == ""  # a new run of failures starts over
    assert retries.succeeded() == "after 1 failed try since 21:03:20"


async def test_a_peer_asking_while_our_token_was_just_dropped_waits_for_the_refresh():
    """ROS 2 audit: a grant change revokes our token (the feed says so, the keeper drops
    it and asks again at once); a peer's stream opened in between was refused ``no_token``
    every time. It now gets its token once the refresh is in."""
    authz = Authz("robot_a")
    keeper = TokenKeeper(authz, refresh_margin=60, manager="robot_a")
    runner = asyncio.create_task(keeper.run())
    try:
        await asyncio.wait_for(keeper.refreshed.wait(), 5)
        keeper.invalidate()  # what the gateway does when the feed revokes our token
        token = await asyncio.wait_for(keeper.for_peer("x" * 43), 5)
        assert token and authz.fetches >= 3  # ours again, then the peer's
    finally:
        runner.cancel()


async def test_a_peer_asking_while_no_token_can_be_had_is_refused_after_a_bounded_wait(monkeypatch):
    monkeypatch.setattr(authz_client, "PEER_TOKEN_WAIT", 0.2)

    class Down:
        async def fetch_token(self, *, clock=time.time, resource=None):
            raise TokenError("authz_unreachable", "down")

    keeper = TokenKeeper(Down(), refresh_margin=60, manager="robot_a")
    with pytest.raises(TokenError) as info:
        await asyncio.wait_for(keeper.for_peer("x" * 43), 5)
    assert info.value.reason == "no_token"


class Gated(Authz):
    """``fetch_token`` that waits for ``go`` from the second fetch on (a refresh under
    way for as long as the test holds it), or fails once ``down``."""

    def __init__(self, *subjects: str) -> None:
        super().__init__(*subjects)
        self.go = asyncio.Event()
        self.down = False

    async def fetch_token(self, *, clock=time.time, resource=None):
        if self.fetches >= 1:
            await self.go.wait()
            if self.down:
                self.fetches += 1
                raise TokenError("authz_unreachable", "down")
        return await super().fetch_token(clock=clock, resource=resource)


async def _until(condition, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "not within the bound"
        await asyncio.sleep(0.01)


@pytest.mark.parametrize("outcome", ["taken", "failed"])
async def test_a_dropped_token_is_being_replaced_until_its_successors_request_ends_or_the_bound(outcome):
    """What a ROS 2 robot decided on its token stands while the feed's revocation (a grant
    changed) is answered by the next one: a CI run withdrew every offer and closed every
    inbound stream of a robot in the 40-100 ms of such a refresh. Nothing stands past
    the bound, nor once the attempt failed (no token then: fail closed)."""
    now = [1000.0]
    authz = Gated("robot_a")
    keeper = TokenKeeper(authz, refresh_margin=60, manager="robot_a", clock=lambda: now[0])
    assert not keeper.replacing(2.0)
    runner = asyncio.create_task(keeper.run())
    try:
        await asyncio.wait_for(keeper.refreshed.wait(), 5)
        assert keeper.taken_within(0.5) and not keeper.replacing(2.0)
        now[0] += 10
        assert not keeper.taken_within(3.0)
        keeper.invalidate()  # what the gateway does when the feed revokes our token
        with pytest.raises(TokenError):
            keeper.current()
        assert keeper.replacing(2.0)
        now[0] += 1.5
        assert keeper.replacing(2.0) and not keeper.replacing(1.0)
        now[0] += 1.0
        assert not keeper.replacing(2.0)  # past the bound, whatever the request does
        now[0] -= 1.0
        authz.down = outcome == "failed"
        authz.go.set()
        await _until(lambda: not keeper.replacing(2.0))
        if outcome == "taken":
            assert keeper.current() and keeper.taken_within(0.5)
        else:
            with pytest.raises(TokenError):
                keeper.current()
            assert not keeper.taken_within(3.0)
    finally:
        runner.cancel()


async def test_a_token_revoked_while_its_refresh_fetches_the_peers_tokens_is_fetched_again():
    """A fresh-clone run: a grant change revoked our new token while the refresh was still
    fetching the peers' tokens; the refresh then read the token it had just dropped
    (``None``), the keeper's task died of it, silently, and the robot held no token until
    it was restarted (a minute of ``no_token`` in the test). The keeper now fetches again."""
    class RevokedMidway(Authz):
        armed = False

        async def fetch_token(self, *, clock=time.time, resource=None):
            token = await super().fetch_token(clock=clock, resource=resource)
            if self.armed and resource is None:  # a peer's token came in meanwhile (a stream asked)
                keeper._peer_tokens["x" * 43] = token
            elif self.armed:  # the refresh fetches it again: the feed revokes our new token meanwhile
                self.armed = False
                keeper.invalidate()
            return token

    authz = RevokedMidway("robot_a")
    keeper = TokenKeeper(authz, refresh_margin=60, manager="robot_a")
    runner = asyncio.create_task(keeper.run())
    try:
        await asyncio.wait_for(keeper.refreshed.wait(), 5)
        authz.armed = True
        keeper.invalidate()  # a grant change: ours again, then the peer's (revoking ours midway)
        deadline = time.monotonic() + 5
        while True:
            try:
                keeper.current()
                break
            except TokenError:
                assert not runner.done(), runner.exception()
                assert time.monotonic() < deadline, "no token held 5 s after the revocation"
                await asyncio.sleep(0.01)
        assert authz.fetches >= 4 and not runner.done()
    finally:
        runner.cancel()
