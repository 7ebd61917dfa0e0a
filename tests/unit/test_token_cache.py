"""The verified-token cache of the interceptor's :class:`PeerVerifier`: real tokens
(RS256, signed by a real key) bound to real certificates of a throwaway CA.

The same token arrives on many streams, so its signature and claims are decoded once;
everything that depends on the stream (the certificate it came over, the clock, the
revocation feed) is checked on every stream, hit or miss.
"""

from __future__ import annotations

import time

import pytest
from cryptography.hazmat.primitives.asymmetric import rsa

from cryptoros.errors import TokenError
from cryptoros.pemfiles import cert_serial
from cryptoros.tokens import KeySet, Revocations, VerifiedTokenCache, public_jwk, verify_access_token
from interceptor.verifier import PeerVerifier
from tests.verifier_support import (  # noqa: F401 (signing_key, certs: fixtures)
    AUD,
    ISS,
    LIFETIME,
    NOW,
    Clock,
    certs,
    make_verifier,
    signing_key,
    token_for,
)


def reason(fn) -> str:
    with pytest.raises(TokenError) as info:
        fn()
    return info.value.reason


def test_a_cached_token_still_fails_for_a_different_peer_certificate(signing_key, certs):
    verifier = make_verifier(signing_key, Clock(NOW + 10))
    token = token_for(signing_key, certs["alice"])
    first = verifier.verify(token, certs["alice"])
    assert (verifier.token_cache.misses, verifier.token_cache.hits, len(verifier.token_cache)) == (1, 0, 1)
    assert verifier.verify(token, certs["alice"]) is first  # a hit, the same verified token
    assert verifier.token_cache.hits == 1
    assert reason(lambda: verifier.verify(token, certs["bob"])) == "cnf_mismatch"  # replayed over bob's TLS
    assert verifier.token_cache.hits == 2  # the refusal came from the cached decode, not from a new one
    assert reason(lambda: verifier.verify(token, None)) == "no_peer_certificate"
    assert reason(lambda: verifier.verify(token, b"")) == "no_peer_certificate"
    assert verifier.verify(token, certs["alice"]).subject == "alice"  # the right one is not harmed


def test_a_token_revoked_by_the_feed_is_refused_on_the_next_stream_though_cached(signing_key, certs):
    clock = Clock(NOW + 10)
    verifier = make_verifier(signing_key, clock)
    token = token_for(signing_key, certs["alice"])
    access = verifier.verify(token, certs["alice"])
    verifier.verify(token, certs["alice"])
    assert verifier.token_cache.hits == 1
    verifier.apply(Revocations(revoked_jtis=frozenset({access.jti}), serial=2))
    assert reason(lambda: verifier.verify(token, certs["alice"])) == "revoked"
    assert len(verifier.token_cache) == 0  # the new feed emptied it, and a refused token is not kept


@pytest.mark.parametrize("how", ["disabled_manager", "certificate_revoked", "registry_changed"])
def test_every_change_of_the_feed_empties_the_cache_and_its_checks_run_on_hits(signing_key, certs, how):
    verifier = make_verifier(signing_key, Clock(NOW + 10))
    verifier.apply(Revocations(serial=1))
    token = token_for(signing_key, certs["alice"])
    verifier.verify(token, certs["alice"])
    assert len(verifier.token_cache) == 1
    feed = {
        "disabled_manager": Revocations(disabled_subjects=frozenset({"alice"}), serial=2),
        "certificate_revoked": Revocations(revoked_serials=frozenset({cert_serial(certs["alice"])}), serial=1),
        "registry_changed": Revocations(serial=2),  # a grant changed: the feed does not say whose
    }[how]
    verifier.apply(feed)
    if how == "registry_changed":
        assert verifier.verify(token, certs["alice"]).subject == "alice"
        assert (verifier.token_cache.misses, verifier.token_cache.hits) == (2, 0)  # decoded again
    else:
        expected = {"disabled_manager": "subject_disabled", "certificate_revoked": "certificate_revoked"}[how]
        assert reason(lambda: verifier.verify(token, certs["alice"])) == expected
        assert len(verifier.token_cache) == 0


def test_the_per_stream_checks_run_on_a_hit_even_with_the_cache_left_filled(signing_key, certs):
    """The cache itself, with a feed it was not emptied for (the same Revocations object
    cannot change; a new one empties it): a hit still checks the feed it is given."""
    cache = VerifiedTokenCache(16)
    keys = KeySet.from_jwks({"keys": [public_jwk(signing_key.public_key(), "k1")]})
    token = token_for(signing_key, certs["alice"])
    kw = dict(keys=keys, issuer=ISS, audience=AUD, now=NOW + 10)
    access = cache.verify(token, peer_cert_der=certs["alice"], **kw)
    revoked = Revocations(revoked_jtis=frozenset({access.jti}))
    cache._inputs = (keys, ISS, AUD, revoked)  # as if the cache had been filled under this feed
    assert reason(lambda: cache.verify(token, peer_cert_der=certs["alice"], revocations=revoked, **kw)) == "revoked"
    assert cache.hits == 1


def test_an_expired_token_is_refused_from_the_cache_with_the_full_verifys_leeway(signing_key, certs):
    clock = Clock(NOW + 10)
    verifier = make_verifier(signing_key, clock)
    keys = verifier.keys
    token = token_for(signing_key, certs["alice"])
    verifier.verify(token, certs["alice"])
    exp = NOW + LIFETIME
    clock.now = exp + 4.5  # within the 5 s leeway: the full verify accepts it, so does a hit
    verify_access_token(token, keys=keys, issuer=ISS, audience=AUD, peer_cert_der=certs["alice"], now=clock.now)
    assert verifier.verify(token, certs["alice"]).expires_at == exp
    assert verifier.token_cache.hits == 1
    clock.now = exp + 5.0
    assert reason(lambda: verify_access_token(token, keys=keys, issuer=ISS, audience=AUD,
                                              peer_cert_der=certs["alice"], now=clock.now)) == "expired"
    assert reason(lambda: verifier.verify(token, certs["alice"])) == "expired"
    assert verifier.token_cache.hits == 2 and len(verifier.token_cache) == 0  # dropped: never outlives exp
    assert reason(lambda: verifier.verify(token, certs["alice"])) == "expired"  # and a miss refuses it too


def test_a_key_rotation_empties_the_cache_and_a_removed_key_refuses_its_tokens(signing_key, certs):
    verifier = make_verifier(signing_key, Clock(NOW + 10))
    token = token_for(signing_key, certs["alice"])
    verifier.verify(token, certs["alice"])
    same = KeySet.from_jwks({"keys": [public_jwk(signing_key.public_key(), "k1")]})
    verifier.keys = same  # the JWKS fetched again, unchanged (every minute): the cache is kept
    verifier.verify(token, certs["alice"])
    assert verifier.token_cache.hits == 1
    new_key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    verifier.keys = KeySet.from_jwks({"keys": [public_jwk(new_key.public_key(), "k2")]})  # k1 retired
    assert reason(lambda: verifier.verify(token, certs["alice"])) == "unknown_kid"
    assert len(verifier.token_cache) == 0
    # a key replaced under the same kid: the old token's signature no longer verifies
    verifier.keys = KeySet.from_jwks({"keys": [public_jwk(new_key.public_key(), "k1")]})
    assert reason(lambda: verifier.verify(token, certs["alice"])) == "bad_signature"


def test_a_narrowed_audience_change_empties_the_cache(signing_key, certs):
    verifier = make_verifier(signing_key, Clock(NOW + 10))
    token = token_for(signing_key, certs["alice"])
    verifier.verify(token, certs["alice"])
    verifier.own_audience = "urn:cryptoros:peer:" + "A" * 43  # a reload with a renewed certificate
    verifier.verify(token, certs["alice"])
    assert (verifier.token_cache.misses, verifier.token_cache.hits) == (2, 0)


def test_the_cache_stays_bounded_under_many_distinct_tokens(signing_key, certs):
    verifier = make_verifier(signing_key, Clock(NOW + 10), token_cache_size=32)
    tokens = [token_for(signing_key, certs["alice"], now=NOW - i) for i in range(100)]
    for token in tokens:
        verifier.verify(token, certs["alice"])
        assert len(verifier.token_cache) <= 32
    assert len(verifier.token_cache) == 32
    verifier.verify(tokens[-1], certs["alice"])  # the most recent ones are kept
    assert verifier.token_cache.hits == 1
    verifier.verify(tokens[0], certs["alice"])  # the oldest was dropped: decoded again
    assert verifier.token_cache.misses == 101
    assert PeerVerifier.TOKEN_CACHE_SIZE == 4096  # the default bound
    with pytest.raises(ValueError):
        VerifiedTokenCache(0)


def test_garbage_and_refused_tokens_are_never_cached(signing_key, certs, other_pki):
    verifier = make_verifier(signing_key, Clock(NOW + 10))
    forged = token_for(rsa.generate_private_key(public_exponent=65537, key_size=2048), certs["alice"])
    for bad, why in ((forged, "bad_signature"), ("not.a.token", "malformed"), ("x" * 70_000, "malformed")):
        assert reason(lambda bad=bad: verifier.verify(bad, certs["alice"])) == why
    token = token_for(signing_key, certs["alice"])
    assert reason(lambda: verifier.verify(token, certs["bob"])) == "cnf_mismatch"  # never passed: not kept
    assert len(verifier.token_cache) == 0
    assert reason(lambda: verifier.verify(token, certs["bob"])) == "cnf_mismatch"
    assert verifier.token_cache.hits == 0


def test_a_hit_is_much_cheaper_than_a_miss(signing_key, certs):
    """Measured and printed (-s), not asserted: timings on a shared machine flake."""
    clock = Clock(NOW + 10)
    verifier = make_verifier(signing_key, clock)
    verifier.apply(Revocations(revoked_jtis=frozenset(f"jti{i}" for i in range(10_000)), serial=1))
    token = token_for(signing_key, certs["alice"])
    n = 300

    def per_call(fn) -> float:
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            for _ in range(n):
                fn()
            best = min(best, (time.perf_counter() - t0) / n * 1e6)
        return best

    def miss():
        verifier.token_cache.clear()
        return verifier.verify(token, certs["alice"])

    miss_us = per_call(miss)
    hit_us = per_call(lambda: verifier.verify(token, certs["alice"]))
    print(f"\nPeerVerifier.verify per stream: miss (full verify) {miss_us:.1f} us, hit {hit_us:.1f} us, "
          f"{miss_us / hit_us:.1f}x (10,000 revoked jtis in the feed)")
    assert verifier.token_cache.hits >= 3 * n and verifier.token_cache.misses >= 3 * n
