"""cryptoros-authz serve as a real subprocess, over real HTTPS with client certificates.

One daemon per module on a free loopback port, a throwaway CA, a SQLite registry
built with the admin CLI. Covers the token endpoint (RFC 6749 4.4 + RFC 8705), JWKS,
the revocation feed, health, metrics, audit rows, key rotation, 200 concurrent token
requests and graceful shutdown.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import time

import aiohttp
import pytest

from cryptoros.tokens import KeySet, verify_access_token
from tests.authz_support import authz, build_team, ok, read_pem_der, stale_tokens_after_revokes
from tests.support import until

ISS, AUD = "cryptoros-authz", "cryptoros"


def claims_of(token: str) -> dict:
    payload = token.split(".")[1]
    return json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))


def header_of(token: str) -> dict:
    h = token.split(".")[0]
    return json.loads(base64.urlsafe_b64decode(h + "=" * (-len(h) % 4)))


def test_token_is_rs256_jwt_bound_to_the_client_certificate_with_grants(daemon):
    status, body = daemon.token("alice")
    assert status == 200, body
    assert body["token_type"] == "Bearer" and body["expires_in"] == 300
    assert daemon.last_headers["Cache-Control"] == "no-store"
    token = body["access_token"]
    hdr = header_of(token)
    assert hdr["alg"] == "RS256" and hdr["typ"] == "at+jwt" and hdr["kid"]
    jwks = daemon.get_json("/.well-known/jwks.json")
    assert hdr["kid"] in [k["kid"] for k in jwks["keys"]]
    alice_der = read_pem_der(daemon.cert_of("alice")[0])
    tok = verify_access_token(token, keys=KeySet.from_jwks(jwks), issuer=ISS, audience=AUD, peer_cert_der=alice_der)
    c = tok.claims
    assert c["sub"] == "alice" and c["iss"] == ISS and c["aud"] == AUD
    assert c["nbf"] == c["iat"] and c["exp"] - c["iat"] == 300 and abs(c["iat"] - time.time()) < 30
    assert len(c["jti"]) >= 16
    assert c["grants"] == {
        "/talker": {"publish": [["/chatter", "std_msgs/String"]]},
        "/listener": {"subscribe": [["/chatter", "std_msgs/String"]]},
        "/adder": {"serve": [["/add_two_ints", "rospy_tutorials/AddTwoInts"]]},
    }
    assert tok.grants.allows("publish", "/talker", "/chatter", "std_msgs/String")
    assert not tok.grants.allows("publish", "/listener", "/chatter", "std_msgs/String")
    # the issue is in the audit log, with the jti and kid
    rows = [json.loads(line) for line in ok(daemon.cli("audit", "--json", "--manager", "alice")).splitlines()]
    assert any(r["event"] == "issued" and r["jti"] == c["jti"] and r["kid"] == hdr["kid"] for r in rows)


def test_a_token_for_one_peer_is_bound_to_it_and_carries_only_what_it_shares(daemon):
    """RFC 8707 resource indicator: alice asks for a token to show bob. It names bob's
    certificate as audience and carries only alice's grants on names bob holds a grant
    on too (need to know); carol, or any verifier not bob, refuses it."""
    import urllib.parse

    from cryptoros.errors import TokenError
    from cryptoros.tls import cert_thumbprint_s256
    from cryptoros.tokens import peer_audience

    thumb = {n: cert_thumbprint_s256(read_pem_der(daemon.cert_of(n)[0])) for n in ("alice", "bob", "carol", "stranger")}

    def for_peer(name: str, resource: str) -> tuple[int, dict]:
        return daemon.token(name, "grant_type=client_credentials&resource=" + urllib.parse.quote(resource, safe=""))

    status, body = for_peer("alice", peer_audience(thumb["bob"]))
    assert status == 200, body
    keys = KeySet.from_jwks(daemon.get_json("/.well-known/jwks.json"))
    alice_der = read_pem_der(daemon.cert_of("alice")[0])
    tok = verify_access_token(body["access_token"], keys=keys, issuer=ISS, audience=(AUD, peer_audience(thumb["bob"])),
                              peer_cert_der=alice_der)
    assert tok.claims["aud"] == peer_audience(thumb["bob"])
    assert tok.claims["grants"] == {"/adder": {"serve": [["/add_two_ints", "rospy_tutorials/AddTwoInts"]]}}
    for audience in (AUD, (AUD, peer_audience(thumb["carol"]))):  # a whole-token verifier, carol
        with pytest.raises(TokenError) as refused:
            verify_access_token(body["access_token"], keys=keys, issuer=ISS, audience=audience, peer_cert_der=alice_der)
        assert refused.value.reason == "bad_audience"
    status, body = for_peer("alice", peer_audience(thumb["carol"]))  # carol shares no name with alice
    assert status == 200 and claims_of(body["access_token"])["grants"] == {}
    rows = [json.loads(line) for line in ok(daemon.cli("audit", "--json", "--manager", "alice")).splitlines()]
    assert any(r["event"] == "issued" and r["jti"] == tok.jti and "for bob" in json.dumps(r) for r in rows)
    for resource in (peer_audience(thumb["stranger"]), "urn:cryptoros:peer:short", "https://bob.example/"):
        assert for_peer("alice", resource) == (400, {"error": "invalid_target"})
    # bob disabled: refused too, and the audit (and log) say it is the peer that is disabled,
    # not alice that was refused for an unknown resource (a day-2 audit)
    ok(daemon.cli("disable-manager", "bob"))
    try:
        until(lambda: for_peer("alice", peer_audience(thumb["bob"]))[0] == 400, 15, "bob's peer token refused")
        rows = [json.loads(line) for line in ok(daemon.cli("audit", "--json", "--manager", "alice")).splitlines()]
        assert any(r["event"] == "denied" and "peer_disabled (a token for bob, which is disabled)" in json.dumps(r)
                   for r in rows), rows[-3:]
    finally:
        ok(daemon.cli("enable-manager", "bob"))
        until(lambda: daemon.token("bob")[0] == 200, 15, "bob's tokens issued again")  # the server's cache


def test_the_start_up_line_names_the_registry_it_serves(daemon):
    """CRYPTOROS_AUTHZ_DB, a configuration file's db and --db can each name one: the
    operator reads which one the daemon opened (a password would be masked)."""
    line = next((line for line in daemon.log().splitlines() if "serving on https://" in line), "")
    assert f"registry {daemon.db}," in line, daemon.log()[-2000:]


def test_each_token_has_a_fresh_jti(daemon):
    jtis = {claims_of(daemon.token("bob")[1]["access_token"])["jti"] for _ in range(3)}
    assert len(jtis) == 3


def test_wildcard_node_grant_is_carried_explicitly(daemon):
    status, body = daemon.token("carol")
    assert status == 200
    assert claims_of(body["access_token"])["grants"] == {"*": {"subscribe": [["/scan", "sensor_msgs/msg/LaserScan"]]}}


def test_unregistered_certificate_gets_invalid_client_and_an_audit_row(daemon):
    status, body = daemon.token("stranger")
    assert (status, body) == (401, {"error": "invalid_client"})
    rows = [json.loads(x) for x in ok(daemon.cli("audit", "--json", "--event", "denied")).splitlines()]
    assert any(r["reason"] == "unknown_certificate" and r["manager"] is None for r in rows), rows
    assert "token denied" in daemon.log() and "reason=unknown_certificate" in daemon.log()


def test_a_certificate_bound_to_another_managers_name_gets_no_token(daemon):
    """Policy audit: ``import`` (and ``set-cert --fingerprint``) bind a fingerprint without
    the certificate; with robot1's and robot2's fingerprints swapped in a policy file,
    robot2's interceptor got robot1's tokens. A certificate naming another holder than
    the manager its fingerprint is bound to is refused at every token request."""
    hank = daemon.team.pki.issue("hank", kind="interceptor")
    ok(daemon.cli("add-manager", "ivy", "--fingerprint", hank.fingerprint_sha256))
    refused = "manager=ivy fingerprint={} remote=127.0.0.1 reason=certificate_identity identifies interceptor " \
              "'hank', not manager 'ivy'".format(hank.fingerprint_sha256[:16])
    deadline = time.monotonic() + 10  # until the replica re-read the managers (unknown until then)
    while refused not in daemon.log():
        assert daemon.token("hank") == (401, {"error": "invalid_client"})
        assert time.monotonic() < deadline, daemon.log()[-2000:]
        time.sleep(0.1)
    rows = [json.loads(x) for x in ok(daemon.cli("audit", "--json", "--event", "denied")).splitlines()]
    assert any(r["manager"] == "ivy" and r["reason"].startswith("certificate_identity") for r in rows), rows
    ok(daemon.cli("remove-manager", "ivy"))
    ok(daemon.cli("add-manager", "hank", "--fingerprint", hank.fingerprint_sha256))
    deadline = time.monotonic() + 10
    while daemon.token("hank")[0] != 200:  # its own manager's name: served
        assert time.monotonic() < deadline
        time.sleep(0.1)


@pytest.mark.parametrize(
    "body, status, error",
    [
        ("", 400, "invalid_request"),
        ("grant_type=password&username=a&password=b", 400, "unsupported_grant_type"),
        ("grant_type=authorization_code&code=x", 400, "unsupported_grant_type"),
        ("grant_type=client_credentials&grant_type=client_credentials", 400, "invalid_request"),
        ("grant_type=client_credentials&client_id=bob", 401, "invalid_client"),
    ],
)
def test_bad_token_requests_get_opaque_oauth_errors(daemon, body, status, error):
    got_status, got = daemon.token("alice", body=body)
    assert (got_status, got) == (status, {"error": error})


def test_client_id_matching_the_certificate_is_accepted(daemon):
    status, body = daemon.token("alice", body="grant_type=client_credentials&client_id=alice&scope=ignored")
    assert status == 200 and claims_of(body["access_token"])["sub"] == "alice"


def test_get_on_token_endpoint_is_not_allowed(daemon):
    cert, key = daemon.cert_of("alice")
    status, _ = daemon.request("GET", "/token", cert=cert, key=key)
    assert status == 405


def test_healthz_and_prometheus_metrics(daemon):
    health = daemon.get_json("/healthz")
    assert health["status"] == "ok" and health["database"] == "ok" and health["kid"]
    assert health["certificate"] == "ok"  # expires in over CERT_WARN_DAYS (else "expires in N days")
    daemon.token("alice")
    daemon.token("stranger")
    cert, key = daemon.cert_of("probe")
    status, raw = daemon.request("GET", "/metrics", cert=cert, key=key)
    text = raw.decode()
    assert status == 200 and daemon.last_headers["Content-Type"].startswith("text/plain")
    issued = [float(line.split()[-1]) for line in text.splitlines()
              if line.startswith("cryptoros_authz_tokens_issued_total ")]
    assert issued and issued[0] >= 1
    assert 'cryptoros_authz_token_denials_total{reason="unknown_certificate"}' in text
    assert 'cryptoros_authz_request_duration_seconds_bucket{endpoint="/token",le=' in text


def test_revocation_feed_lists_revoked_jti_and_supports_etag(daemon):
    _, body = daemon.token("bob")
    jti = claims_of(body["access_token"])["jti"]
    feed = daemon.get_json("/revocations")
    assert set(feed) == {"serial", "revoked_jtis", "disabled_managers", "learning", "revoked_serials", "generated_at"}
    assert feed["learning"] == {}  # no manager learns
    assert jti not in feed["revoked_jtis"]
    cert, key = daemon.cert_of("probe")
    status, _ = daemon.request("GET", "/revocations", cert=cert, key=key)
    etag = daemon.last_headers["ETag"]
    status, raw = daemon.request("GET", "/revocations", cert=cert, key=key, headers={"If-None-Match": etag})
    assert status == 304 and raw == b""
    ok(daemon.cli("revoke-token", jti, "--reason", "stolen laptop"))
    deadline = time.monotonic() + 5
    while True:
        status, raw = daemon.request("GET", "/revocations", cert=cert, key=key, headers={"If-None-Match": etag})
        if status == 200:
            break
        assert time.monotonic() < deadline, "feed did not change within 5 s"
        time.sleep(0.2)
    new = json.loads(raw)
    assert jti in new["revoked_jtis"] and new["serial"] > feed["serial"]
    assert daemon.last_headers["ETag"] != etag


def test_a_long_poll_of_the_feed_answers_as_soon_as_it_changes(daemon):
    """Fleet scale: ``/revocations?wait=S`` with the current ETag is held until the feed
    changes (a revocation reaches the waiting interceptor within a watch interval, not
    a poll later) and answers 304 after S seconds when nothing changed: one request per
    S seconds per idle interceptor instead of one a second."""
    import threading

    cert, key = daemon.cert_of("probe")
    daemon.request("GET", "/revocations", cert=cert, key=key)
    etag = daemon.last_headers["ETag"]
    started = time.monotonic()
    status, _ = daemon.request("GET", "/revocations?wait=1.5", cert=cert, key=key, headers={"If-None-Match": etag})
    assert status == 304 and 1.4 <= time.monotonic() - started < 5
    for bad in ("3601", "-1", "nan", "inf", "soon"):
        assert daemon.request("GET", f"/revocations?wait={bad}", cert=cert, key=key)[0] == 400, bad
    _, body = daemon.token("bob")
    jti = claims_of(body["access_token"])["jti"]
    answer: dict = {}

    def long_poll() -> None:
        answer["status"], answer["raw"] = daemon.request("GET", "/revocations?wait=20", cert=cert, key=key,
                                                         headers={"If-None-Match": etag})
        answer["at"] = time.monotonic()

    waiter = threading.Thread(target=long_poll)
    waiter.start()
    daemon.wait_polls_held(1)  # the request is being held
    assert "status" not in answer
    revoked_at = time.monotonic()
    ok(daemon.cli("revoke-token", jti))
    waiter.join(timeout=25)
    assert answer["status"] == 200 and jti in json.loads(answer["raw"])["revoked_jtis"]
    # answered on the change, not at the end of its 20 s wait (the CLI's own start-up
    # included, which a busy machine can stretch to seconds)
    assert answer["at"] - revoked_at < 12.0


def test_two_hundred_concurrent_token_requests_all_succeed_and_verify(daemon):
    jwks = daemon.get_json("/.well-known/jwks.json")
    keys = KeySet.from_jwks(jwks)
    cert, key = daemon.cert_of("alice")
    der = read_pem_der(cert)
    ctx = daemon.context(cert, key)

    async def fetch_all():
        connector = aiohttp.TCPConnector(ssl=ctx, limit=0, force_close=True)
        timeout = aiohttp.ClientTimeout(total=60)
        async with aiohttp.ClientSession(connector=connector, timeout=timeout) as session:
            async def one():
                async with session.post(f"{daemon.base}/token", data={"grant_type": "client_credentials"}) as r:
                    return r.status, await r.json()

            return await asyncio.gather(*(one() for _ in range(200)), return_exceptions=True)

    results = asyncio.run(fetch_all())
    errors = [r for r in results if isinstance(r, BaseException) or r[0] != 200]
    assert not errors, errors[:3]
    jtis = set()
    for _status, body in results:
        tok = verify_access_token(body["access_token"], keys=keys, issuer=ISS, audience=AUD, peer_cert_der=der)
        jtis.add(tok.jti)
    assert len(jtis) == 200
    issued = [json.loads(x) for x in ok(daemon.cli("audit", "--json", "--limit", "100000", "--event",
                                                    "issued")).splitlines()]
    assert jtis <= {r["jti"] for r in issued}


def test_key_rotation_keeps_old_key_published_and_signs_with_the_new(daemon):
    _, body = daemon.token("alice")
    old_token = body["access_token"]
    old_kid = header_of(old_token)["kid"]
    out = ok(authz("rotate-key", "--signing-key-passphrase-file", str(daemon.workdir / "signing.pass"), db=daemon.db))
    new_kid = out.split()[-1]
    assert new_kid != old_kid
    deadline = time.monotonic() + 5
    while header_of(daemon.token("alice")[1]["access_token"])["kid"] != new_kid:
        assert time.monotonic() < deadline, "daemon did not pick up the rotated key"
        time.sleep(0.2)
    jwks = daemon.get_json("/.well-known/jwks.json")
    kids = {k["kid"] for k in jwks["keys"]}
    assert {old_kid, new_kid} <= kids
    der = read_pem_der(daemon.cert_of("alice")[0])
    keys = KeySet.from_jwks(jwks)
    verify_access_token(old_token, keys=keys, issuer=ISS, audience=AUD, peer_cert_der=der)
    new_token = daemon.token("alice")[1]["access_token"]
    verify_access_token(new_token, keys=keys, issuer=ISS, audience=AUD, peer_cert_der=der)


def test_disabled_manager_is_refused_and_listed_in_the_feed(daemon):
    _, body = daemon.token("carol")
    live = body["access_token"]
    ok(daemon.cli("disable-manager", "carol"))
    deadline = time.monotonic() + 5
    while True:
        status, body = daemon.token("carol")
        if status != 200:
            break
        assert time.monotonic() < deadline
        time.sleep(0.2)
    assert (status, body) == (403, {"error": "access_denied"})
    # the feed has its own cache (cache_seconds): the refusal can come before the feed lists it
    deadline = time.monotonic() + 5
    while "carol" not in (feed := daemon.get_json("/revocations"))["disabled_managers"]:
        assert time.monotonic() < deadline, feed
        time.sleep(0.2)
    assert claims_of(live)["jti"] in feed["revoked_jtis"]
    rows = [json.loads(x) for x in ok(daemon.cli("audit", "--json", "--manager", "carol")).splitlines()]
    assert rows[-1]["event"] == "denied" and rows[-1]["reason"] == "manager_disabled"
    ok(daemon.cli("enable-manager", "carol"))


def _until(daemon, name: str, wanted: tuple[int, dict], bound: float = 10.0) -> None:
    """Ask for tokens until the answer is ``wanted`` (a bound for a slow machine, not a
    timing claim: the change reaches the replica within one feed-watcher interval)."""
    deadline = time.monotonic() + bound
    while (got := daemon.token(name)) != wanted:
        assert time.monotonic() < deadline, got
        time.sleep(0.1)


def test_registry_changes_that_revoke_no_token_reach_the_next_token_request(daemon):
    """The daemon keeps a manager's grants in memory until the registry's version moves.
    Changes that revoke no token (so the revocation serial stays) move it too: a
    certificate it has refused as unknown, registered meanwhile, gets tokens; a manager
    that holds no token, moved to a new certificate, is refused on the old one."""
    pki = daemon.team.pki
    frank = pki.issue("frank")
    assert daemon.token("frank") == (401, {"error": "invalid_client"})  # now known as unknown
    ok(daemon.cli("add-manager", "frank", "--fingerprint", frank.fingerprint_sha256))
    deadline = time.monotonic() + 10
    while (status := daemon.token("frank")[0]) != 200:
        assert status == 401 and time.monotonic() < deadline, status
        time.sleep(0.1)

    erin_old = pki.issue("erin")
    _, erin_new = pki.renew_keeping_old("erin", "erin_old")
    ok(daemon.cli("add-manager", "erin", "--fingerprint", erin_old.fingerprint_sha256, "--disabled"))
    _until(daemon, "erin_old", (403, {"error": "access_denied"}))  # erin's old certificate, known: no token issued
    ok(daemon.cli("set-cert", "erin", "--fingerprint", erin_new.fingerprint_sha256))
    _until(daemon, "erin_old", (401, {"error": "invalid_client"}))  # the old certificate is nobody's now
    assert daemon.token("erin") == (403, {"error": "access_denied"})  # the new one is erin's, still disabled


def test_a_token_asked_for_just_after_a_grant_is_revoked_never_carries_it(daemon):
    """Security audit (HIGH): the daemon serves a manager's grants from memory until its
    feed watcher reads the registry's new version (up to FEED_WATCH_INTERVAL later), and
    a revoke revokes the tokens issued before it. A token asked for in between carried
    the removed grant, unrevoked, for its whole lifetime: an insider asking for tokens
    continuously kept a subscription the operator took away. Now the token's audit row
    is stored only if the registry is still at the version its grants were read at (else
    it is built again): no token asked for after the revoke returned carries the grant."""
    assert stale_tokens_after_revokes(daemon, daemon, "carol") == []


def test_a_planned_renewal_with_an_overlap_serves_both_certificates_then_only_the_new(daemon):
    """``set-cert --overlap``: the running daemon issues tokens to the old certificate and
    to the new one (each bound to the certificate that asked), revokes none; after the
    overlap only the new one gets tokens."""
    import ssl

    import jwt

    from cryptoros.tls import cert_thumbprint_s256

    pki = daemon.team.pki
    gina_old = pki.issue("gina")
    old_path, gina_new = pki.renew_keeping_old("gina", "gina_old")
    ok(daemon.cli("add-manager", "gina", "--fingerprint", gina_old.fingerprint_sha256))
    deadline = time.monotonic() + 10
    while (answer := daemon.token("gina_old"))[0] != 200:  # known once the replica re-read the managers
        assert time.monotonic() < deadline, answer
        time.sleep(0.1)
    first = answer[1]
    out = ok(daemon.cli("set-cert", "gina", "--fingerprint", gina_new.fingerprint_sha256, "--overlap", "4"))
    assert "accepted for 4 s more" in out, out
    deadline = time.monotonic() + 10
    while daemon.token("gina")[0] != 200:  # the new one, once the replica re-read the manager
        assert time.monotonic() < deadline
        time.sleep(0.1)
    for name, path in (("gina_old", old_path), ("gina", gina_new.cert_path)):
        status, body = daemon.token(name)
        assert status == 200, (name, body)
        claims = jwt.decode(body["access_token"], options={"verify_signature": False})
        der = ssl.PEM_cert_to_DER_cert(path.read_text())
        assert claims["sub"] == "gina" and claims["cnf"]["x5t#S256"] == cert_thumbprint_s256(der)
    feed = daemon.get_json("/revocations")
    assert jwt.decode(first["access_token"], options={"verify_signature": False})["jti"] not in feed["revoked_jtis"]
    _until(daemon, "gina_old", (401, {"error": "invalid_client"}), bound=15)  # the overlap is over
    assert daemon.token("gina")[0] == 200


def test_certificate_revoked_while_running_is_refused_within_seconds(daemon):
    # a manager registered and working...
    daemon.team.pki.issue("dave")
    ok(daemon.cli("add-manager", "dave", "--cert", str(daemon.cert_of("dave")[0])))
    deadline = time.monotonic() + 5
    while daemon.token("dave")[0] != 200:
        assert time.monotonic() < deadline
        time.sleep(0.2)
    # ...whose certificate the CA revokes: the daemon re-reads the CRL, no restart
    daemon.team.pki.revoke("dave")
    deadline = time.monotonic() + 5
    while (got := daemon.token("dave")) != (401, {"error": "invalid_client"}):
        assert got[0] == 200 and time.monotonic() < deadline, got
        time.sleep(0.2)
    rows = [json.loads(x) for x in ok(daemon.cli("audit", "--json", "--event", "denied")).splitlines()]
    assert any(r["reason"] == "certificate_revoked" for r in rows)
    cert, key = daemon.cert_of("dave")
    assert daemon.request("GET", "/revocations", cert=cert, key=key)[0] == 401
    assert daemon.token("alice")[0] == 200


def test_sighup_reloads_the_tls_material_and_a_bad_one_is_kept_out(daemon):
    """Day 2: the authorization server's certificate is renewed and the daemon gets
    SIGHUP: it keeps running (not killed by the signal), new connections get the new
    certificate and tokens are issued; a broken file on the next SIGHUP is one log line
    and the daemon keeps serving with what it had."""
    import signal
    import socket

    def served_serial() -> int:
        ctx = daemon.context(*daemon.cert_of("alice"))
        with socket.create_connection((daemon.host, daemon.port), timeout=10) as raw, \
                ctx.wrap_socket(raw, server_hostname=daemon.host) as tls:
            from cryptography import x509

            return x509.load_der_x509_certificate(tls.getpeercert(binary_form=True)).serial_number

    def hup_until(needle: str) -> None:
        before = len(daemon.log())
        daemon.proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 15
        while needle not in daemon.log()[before:]:
            assert daemon.proc.poll() is None, daemon.log()[-2000:]
            assert time.monotonic() < deadline, daemon.log()[before:][-2000:]
            time.sleep(0.05)

    old = served_serial()
    renewed = daemon.pki.issue("authz", kind="server", force=True)  # same files, new key and serial
    hup_until("reloaded TLS material")
    assert served_serial() == renewed.serial != old
    assert daemon.token("alice")[0] == 200
    good = renewed.cert_path.read_bytes()
    try:
        renewed.cert_path.write_text("not a certificate\n")
        hup_until("reload failed, keeping the old TLS material")
        assert served_serial() == renewed.serial and daemon.token("bob")[0] == 200
    finally:
        renewed.cert_path.write_bytes(good)
    assert daemon.proc.poll() is None


def test_an_insider_cannot_hold_more_than_four_long_polls(daemon):
    """Long-polls hold connections: a client certificate gets at most four held at once;
    a fifth is answered at once (304), so one insider cannot pin the server's
    connections; other clients are not affected."""
    import threading

    cert, key = daemon.cert_of("alice")
    daemon.request("GET", "/revocations", cert=cert, key=key)
    etag = daemon.last_headers["ETag"]
    done: list[float] = []

    def hold() -> None:
        daemon.request("GET", "/revocations?wait=4", cert=cert, key=key, headers={"If-None-Match": etag})
        done.append(time.monotonic())

    holders = [threading.Thread(target=hold) for _ in range(4)]
    for t in holders:
        t.start()
    daemon.wait_polls_held(4)
    started = time.monotonic()
    status, _ = daemon.request("GET", "/revocations?wait=4", cert=cert, key=key, headers={"If-None-Match": etag})
    assert status == 304 and time.monotonic() - started < 1.5 and not done
    for t in holders:
        t.join(timeout=15)
    assert len(done) == 4


def test_a_long_poll_is_held_at_most_the_replicas_max_feed_wait(tmp_path):
    """A client may ask for a longer wait than the replica holds (``max_feed_wait``, a
    config key): it gets its 304 when the replica's maximum is up, and asks again."""
    from tests.authz_support import running_daemon

    team = build_team(tmp_path)
    config = tmp_path / "authz.toml"
    config.write_text("max_feed_wait = 1.0\n")
    with running_daemon(team.pki, team.db, tmp_path, extra=("--config", str(config))) as d:
        cert, key = d.cert_of("alice")
        d.request("GET", "/revocations", cert=cert, key=key)
        etag = d.last_headers["ETag"]
        # 600 s asked, held 1 s: answered well within this request's 10 s socket timeout
        status, _ = d.request("GET", "/revocations?wait=600", cert=cert, key=key, headers={"If-None-Match": etag})
        assert status == 304


def test_a_server_started_without_a_crl_says_what_it_then_misses(tmp_path, daemon):
    """No CRL configured: a certificate revoked at the CA still gets tokens while it is
    bound to its manager (mallory, revoked in the team's CRL, here). Allowed, but said at
    start; the fixture's server, started with one, says nothing of it."""
    from tests.authz_support import running_daemon

    assert "no CRL" not in daemon.log()
    team = build_team(tmp_path)
    with running_daemon(team.pki, team.db, tmp_path, crl=False) as d:
        assert "WARNING no CRL (--crl, or crl = in the configuration): a certificate revoked" in d.log(), d.log()
        assert d.token("mallory")[0] == 200


def test_a_server_whose_secret_files_others_may_read_says_which_at_start(tmp_path, daemon):
    """Its TLS key and the signing keys' passphrase file open to the group (0640): one
    warning each at start naming the file, its mode and chmod 600; the fixture's server,
    its files 0600, says nothing of it."""
    from tests.authz_support import running_daemon

    assert "chmod 600" not in daemon.log(), daemon.log()
    team = build_team(tmp_path)
    with running_daemon(team.pki, team.db, tmp_path, secret_mode=0o640) as d:
        key = team.pki.pki.key_path_for("authz")
        for line in (f"WARNING the TLS key {key} has mode 0640, open to its group on this host: chmod 600 {key}",
                     f"WARNING the signing keys' passphrase file {tmp_path / 'signing.pass'} has mode 0640, open to "
                     f"its group on this host: chmod 600 {tmp_path / 'signing.pass'}"):
            assert line in d.log(), d.log()


def test_failed_tls_handshakes_are_counted_in_metrics(daemon):
    """Bytes that are not TLS at the public port: a failed handshake, counted in
    cryptoros_authz_tls_handshakes_refused_total (the warning: test_authz_listener.py)."""
    import socket

    def refused() -> float:
        cert, key = daemon.cert_of("probe")
        _status, raw = daemon.request("GET", "/metrics", cert=cert, key=key)
        return next(float(line.split()[1]) for line in raw.decode().splitlines()
                    if line.startswith("cryptoros_authz_tls_handshakes_refused_total "))

    before = refused()
    for _ in range(3):
        with socket.create_connection(("127.0.0.1", daemon.port), timeout=5) as sock:
            sock.sendall(b"GET / HTTP/1.1\r\n\r\n")
            sock.recv(1)  # closed by the server
    deadline = time.monotonic() + 10
    while refused() < before + 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert refused() == before + 3


def test_healthz_says_unavailable_while_the_registry_fails_requests(daemon):
    """A registry that answers reads but fails writes (a full disk) answered every token
    request 503 while /healthz said ok, so a load balancer kept sending robots to it.
    Simulated here by a trigger that fails every audit row, then dropped."""
    import sqlite3

    path = daemon.db.removeprefix("sqlite:///")
    assert daemon.token("alice")[0] == 200 and daemon.get_json("/healthz")["status"] == "ok"
    with contextlib.closing(sqlite3.connect(path)) as db, db:
        db.execute("CREATE TRIGGER full_disk BEFORE INSERT ON audit_log BEGIN SELECT RAISE(FAIL, 'database or disk "
                   "is full'); END")
    try:
        deadline = time.monotonic() + 10
        while daemon.token("alice")[0] != 503:
            assert time.monotonic() < deadline, "token requests did not fail with the registry failing writes"
            time.sleep(0.2)
        cert, key = daemon.cert_of("probe")
        status, body = daemon.request("GET", "/healthz", cert=cert, key=key)
        assert status == 503 and json.loads(body)["database"] == "failing", (status, body)
    finally:
        with contextlib.closing(sqlite3.connect(path)) as db, db:
            db.execute("DROP TRIGGER full_disk")
    assert daemon.token("alice")[0] == 200  # a token issued again: healthy at once
    assert daemon.get_json("/healthz")["status"] == "ok"


def test_a_certificate_holder_cannot_hold_more_than_its_connections_nor_keep_an_unfinished_request(tmp_path):
    """Insider audit: past the TLS handshake nothing bounded a client's connections; one
    certificate holder left 20,000 request heads unfinished and the daemon ran out of
    descriptors (2.8 GB), every robot's token renewal timing out. Now a certificate holds
    at most ``max_connections_per_client``; with ``max_connections`` reached, the
    certificate holding the most gives way; an unfinished request head is closed after
    ``idle_timeout``."""
    import socket

    from tests.authz_support import running_daemon

    team = build_team(tmp_path)
    config = tmp_path / "authz.toml"
    config.write_text("max_connections_per_client = 3\nmax_connections = 5\nidle_timeout = 3.0\n")
    with running_daemon(team.pki, team.db, tmp_path, extra=("--config", str(config))) as d:
        def hold(name: str):
            s = d.context(*d.cert_of(name)).wrap_socket(socket.create_connection(("127.0.0.1", d.port), timeout=10),
                                                        server_hostname="127.0.0.1")
            s.sendall(b"POST /token HTTP/1.1\r\nHost: x\r\n")  # a request head never finished
            return s

        def closed_by_server(s, within: float) -> bool:
            s.settimeout(within)
            try:
                return s.recv(1) == b""
            except TimeoutError:
                return False
            except OSError:  # a reset, or TLS's own error for an aborted connection
                return True

        alice = [hold("alice") for _ in range(3)]
        fourth = hold("alice")
        assert closed_by_server(fourth, 5), "a fourth connection of one certificate was kept"
        assert not closed_by_server(alice[0], 0.5)
        assert d.token("bob")[0] == 200  # another certificate is served beside them
        bob = [hold("bob") for _ in range(2)]  # 5 open in all
        assert d.token("carol")[0] == 200  # in all reached: alice, holding the most, gave way
        assert closed_by_server(alice[0], 5), "the oldest connection of the certificate holding the most was kept"
        for s in alice[1:] + bob:  # unfinished heads: closed once idle_timeout passed
            assert closed_by_server(s, 10), "an unfinished request head was kept past idle_timeout"
        assert "connections of certificate" in d.log() and "closed after their handshake" in d.log()
        assert d.token("alice")[0] == 200
