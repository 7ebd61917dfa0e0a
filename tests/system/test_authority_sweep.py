"""The verifier's sweep, on loopback: a stream is cut on time whatever the
authorization server does, and whichever end's token lapsed.

A hung server (it accepts TCP and never answers TLS: a host gone quiet, a stopped
process) holds every request for its whole timeout; none of that may delay a cut.
"""

from __future__ import annotations

import asyncio
import socket
import ssl
import time

from cryptography.hazmat.primitives.asymmetric import rsa

from cryptoros.grants import Grant, Grants
from cryptoros.tokens import KeySet, build_claims, public_jwk, sign_token
from interceptor.authz_client import AuthzClient
from interceptor.verifier import PeerVerifier
from interceptor.config import AuthzSettings

KEY = rsa.generate_private_key(public_exponent=65537, key_size=2048)
DER = b"robot B's certificate"


def verifier_against(url: str, *, grace: float, poll: float = 0.2) -> PeerVerifier:
    ctx = ssl.create_default_context()
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    verifier = PeerVerifier(AuthzClient(AuthzSettings(url=url, request_timeout=3.0), ctx), issuer="cryptoros-authz",
                            audience="cryptoros", poll_interval=poll, grace=grace)
    verifier.keys = KeySet.from_jwks({"keys": [public_jwk(KEY.public_key(), "k1")]})
    return verifier


def token(verifier: PeerVerifier, lifetime: int):
    claims = build_claims(issuer="cryptoros-authz", audience="cryptoros", subject="robot_b",
                          grants=Grants([Grant(node="*", action="subscribe", name="/chatter", type="std_msgs/String")]),
                          cert_der=DER, now=int(time.time()), lifetime=lifetime)
    return verifier.note(verifier.verify(sign_token(claims, KEY, "k1"), DER))


async def test_a_hung_authorization_server_does_not_hold_back_an_expiry_cut():
    hung = socket.socket()
    hung.bind(("127.0.0.1", 0))
    hung.listen(16)  # connections complete in the backlog; nobody ever answers the ClientHello
    verifier = verifier_against(f"https://127.0.0.1:{hung.getsockname()[1]}", grace=1.0)
    access = token(verifier, lifetime=1)
    cut = asyncio.get_running_loop().create_future()
    verifier.watch(access, lambda reason: cut.done() or cut.set_result((reason, time.time())))
    counted: list[str] = []
    verifier.cut_listeners.append(counted.append)
    runner = asyncio.create_task(verifier.run())  # the JWKS is due at once: held 2 x 3 s by the hung server
    try:
        reason, at = await asyncio.wait_for(cut, 10)
    finally:
        runner.cancel()
        hung.close()
        await verifier._client.close()
    assert reason.startswith("token_expired")
    assert counted == ["token_expired"]
    # due at expiry + grace; the sweep runs every 0.2 s: not after the 6 s the server holds a request
    assert access.expires_at + verifier.grace <= at < access.expires_at + verifier.grace + 1.5


def test_every_stream_is_cut_once_our_own_token_expired_past_the_grace():
    verifier = verifier_against("https://127.0.0.1:9", grace=2.0)
    peer = token(verifier, lifetime=300)  # the peer's token: fresh
    cuts: list[str] = []
    verifier.watch(peer, cuts.append)
    counted: list[str] = []
    verifier.cut_listeners.append(counted.append)
    own = [time.time() - 1]  # ours expired 1 s ago: within the grace
    verifier.own_expiry = lambda: own[0]
    assert verifier.sweep() == 0 and not cuts
    own[0] = time.time() - 2.5
    assert verifier.sweep() == 1
    assert cuts[0].startswith("own_token_expired") and counted == ["own_token_expired"]
    assert verifier.open_streams == 0
    own[0] = None  # no token at all (revoked, dropped): the revocation path decides, not this one
    verifier.watch(peer, cuts.append)
    assert verifier.sweep() == 0
