"""How the interceptor's :class:`PeerVerifier` logs the streams it cuts: the streams cut
together (one feed, one sweep, one fresher token) are one line per manager, token and
reason, with how many; every stream is still cut and counted. A disabled robot's streams
were a line each (a day-2 audit: four identical lines; fifty for fifty subscribers)."""

from __future__ import annotations

import logging

from cryptoros.tokens import Revocations
from tests.verifier_support import NOW, Clock, certs, make_verifier, signing_key, token_for  # noqa: F401


def cut_lines(caplog) -> list[str]:
    return sorted(r.getMessage() for r in caplog.records if r.getMessage().startswith("cutting off"))


def test_streams_cut_together_are_one_line_per_manager_token_and_reason(signing_key, certs, caplog):
    verifier = make_verifier(signing_key, Clock(NOW + 10))
    alice = verifier.verify(token_for(signing_key, certs["alice"]), certs["alice"])
    bob = verifier.verify(token_for(signing_key, certs["bob"], subject="bob"), certs["bob"])
    closed: list[str] = []
    counted: list[str] = []
    verifier.cut_listeners.append(counted.append)
    for access in (alice, alice, alice, bob):
        verifier.watch(access, closed.append)
    with caplog.at_level(logging.WARNING, logger="cryptoros.interceptor.authz"):
        assert verifier.apply(Revocations(disabled_subjects=frozenset({"alice", "bob"}), serial=2)) == 4
    assert cut_lines(caplog) == [
        f"cutting off stream of manager=alice jti={alice.jti}: subject_disabled (3 streams)",
        f"cutting off stream of manager=bob jti={bob.jti}: subject_disabled",
    ]
    assert closed == counted == ["subject_disabled"] * 4


def test_a_stream_cut_on_its_own_is_one_line_as_before(signing_key, certs, caplog):
    clock = Clock(NOW + 10)
    verifier = make_verifier(signing_key, clock)
    alice = verifier.verify(token_for(signing_key, certs["alice"]), certs["alice"])
    closed: list[str] = []
    verifier.watch(alice, closed.append)
    clock.now = alice.expires_at + verifier.grace + 1
    with caplog.at_level(logging.WARNING, logger="cryptoros.interceptor.authz"):
        assert verifier.sweep() == 1
    [line] = cut_lines(caplog)
    assert line.startswith(f"cutting off stream of manager=alice jti={alice.jti}: token_expired: ") and \
        not line.endswith("streams)"), line
    assert len(closed) == 1
