"""The registry on a real SQLite file and a real PostgreSQL server.

Every test runs on both backends: SQLite in tmp_path, PostgreSQL as a throwaway
cluster started by tests/postgres_fixture.py (skipped with the reason where the
server is not installed; a failure under CI=true).
"""

from __future__ import annotations

import time
from datetime import UTC, datetime, timedelta

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect, text

from authz_server import db as dbmod
from authz_server.keys import KeyProtection
from authz_server.models import Base
from authz_server.registry import AuditEntry, GrantRow, Registry, new_jti
from cryptoros.errors import ConfigError, RegistryError

pytest_plugins = ["tests.postgres_fixture"]

FP = {n: (c * 64) for n, c in (("alice", "a"), ("bob", "b"), ("carol", "c"), ("dave", "d"))}
UNSAFE = KeyProtection(passphrase=None, unsafe_no_passphrase=True)


TABLES = ("publisher", "subscriber", "service", "service_client", "param_reader", "param_writer", "manager", "revoked_token", "audit_log",
          "signing_key", "registry_state", "registry_change")


@pytest.fixture(params=["sqlite", "postgres"])
def db_url(request, tmp_path):
    """An empty database: a new SQLite file, or a new database on the cluster."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'registry.db'}"
    return request.getfixturevalue("postgres_url")


@pytest.fixture(scope="module")
def _pg_registry(postgres_server):
    """One migrated PostgreSQL database for the module, emptied before each test."""
    import psycopg

    plain = postgres_server.replace("postgresql+psycopg://", "postgresql://")
    with psycopg.connect(plain, autocommit=True, connect_timeout=10) as conn:
        conn.execute('DROP DATABASE IF EXISTS "registry_tests" WITH (FORCE)')
        conn.execute('CREATE DATABASE "registry_tests"')
    url = postgres_server.rsplit("/", 1)[0] + "/registry_tests"
    dbmod.open_registry(url).dispose()
    return url


@pytest.fixture(params=["sqlite", "postgres"])
def reg(request, tmp_path):
    """A migrated registry, empty, on each backend."""
    if request.param == "sqlite":
        engine = dbmod.open_registry(f"sqlite:///{tmp_path / 'registry.db'}", create=True)
    else:
        engine = dbmod.open_registry(request.getfixturevalue("_pg_registry"))
        with engine.begin() as conn:
            conn.execute(text(f"TRUNCATE {', '.join(TABLES)} RESTART IDENTITY CASCADE"))
    try:
        yield Registry(engine)
    finally:
        engine.dispose()


def snapshot(reg: Registry) -> dict:
    return reg.export_policy()


def test_empty_database_is_migrated_to_head_and_matches_the_models(db_url):
    engine = dbmod.open_registry(db_url, create=True)
    reg = Registry(engine)
    assert dbmod.current_revision(reg.engine) == dbmod.head_revision() == dbmod.KNOWN_HEAD
    with reg.engine.connect() as conn:
        diffs = compare_metadata(MigrationContext.configure(conn), Base.metadata)
        tables = set(inspect(conn).get_table_names())
    assert diffs == []
    assert set(TABLES) <= tables
    engine.dispose()


def test_migrations_downgrade_to_base_and_up_again(db_url):
    from alembic import command

    reg = Registry(dbmod.open_registry(db_url, create=True))

    reg.add_manager("alice", FP["alice"])
    cfg = dbmod._alembic_config(reg.engine.url.render_as_string(hide_password=False))
    with reg.engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.downgrade(cfg, "base")
    with reg.engine.connect() as conn:
        assert "manager" not in inspect(conn).get_table_names()
    assert dbmod.upgrade(reg.engine) == dbmod.KNOWN_HEAD
    assert reg.list_managers() == []
    reg.engine.dispose()


def test_a_foreign_database_is_refused(db_url):
    engine = dbmod.make_engine(db_url, create=True)
    with engine.begin() as conn:
        conn.execute(text("CREATE TABLE something_else (id INTEGER PRIMARY KEY)"))
    engine.dispose()
    with pytest.raises(ConfigError, match="not a cryptoros-authz registry"):
        dbmod.open_registry(db_url)


class _Killed(BaseException):
    """A process killed mid-migration, as an exception nothing catches."""


def test_an_interrupted_first_upgrade_leaves_no_registry_file(tmp_path):
    """CLI audit: a first ``db upgrade`` killed mid-way left a file with tables and an
    empty alembic_version, refused by every command after. The new registry is built
    beside it and renamed into place: stopped at the fourth migration, there is none."""
    from sqlalchemy import Engine, event

    path = tmp_path / "registry.db"

    def stop(conn, cursor, statement, *args):
        if statement.lstrip().upper().startswith("CREATE TABLE REGISTRY_CHANGE"):
            raise _Killed

    event.listen(Engine, "before_cursor_execute", stop)
    try:
        with pytest.raises(_Killed):
            dbmod.open_registry(f"sqlite:///{path}", create=True)
    finally:
        event.remove(Engine, "before_cursor_execute", stop)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    engine = dbmod.open_registry(f"sqlite:///{path}", create=True)
    assert dbmod.current_revision(engine) == dbmod.KNOWN_HEAD
    engine.dispose()
    assert path.stat().st_mode & 0o777 == 0o600


def test_a_registry_left_by_an_interrupted_first_upgrade_says_what_to_do(tmp_path):
    """What an older version left when its first upgrade was killed: our tables beside an
    empty alembic_version. The error says so and how to start again, not just 'not ours'."""
    path = tmp_path / "registry.db"
    engine = dbmod.make_engine(f"sqlite:///{path}", create=True)
    Base.metadata.create_all(engine)
    with engine.begin() as conn:
        conn.execute(text("CREATE TABLE alembic_version (version_num VARCHAR(32) NOT NULL PRIMARY KEY)"))
    engine.dispose()
    with pytest.raises(ConfigError) as err:
        dbmod.open_registry(f"sqlite:///{path}", create=True)
    assert "its first 'db upgrade' was interrupted" in str(err.value), err.value
    assert f"remove {path} and run 'cryptoros-authz db upgrade'" in str(err.value), err.value


def test_manager_grants_are_one_to_many_rows_and_found_by_fingerprint(reg):
    reg.add_manager("alice", FP["alice"])
    assert reg.grant("alice", "publish", "/talker", "/chatter", "std_msgs/String") is True
    assert reg.grant("alice", "publish", "/talker", "/chatter", "std_msgs/String") is False  # idempotent
    reg.grant("alice", "subscribe", "/listener", "/chatter", "std_msgs/String")
    reg.grant("alice", "serve", "/adder", "/add_two_ints", "rospy_tutorials/AddTwoInts")
    reg.grant("alice", "call", "/client", "/robot1/get_map", "nav_msgs/srv/GetMap")
    info = reg.lookup_fingerprint(FP["alice"])
    assert info is not None and info.name == "alice" and info.enabled
    assert set(info.grants) == {
        GrantRow("publish", "/talker", "/chatter", "std_msgs/String"),
        GrantRow("subscribe", "/listener", "/chatter", "std_msgs/String"),
        GrantRow("serve", "/adder", "/add_two_ints", "rospy_tutorials/AddTwoInts"),
        GrantRow("call", "/client", "/robot1/get_map", "nav_msgs/srv/GetMap"),
    }
    with reg.engine.connect() as conn:
        counts = {t: conn.execute(text(f"SELECT COUNT(*) FROM {t}")).scalar()
                  for t in ("publisher", "subscriber", "service", "service_client")}
    assert counts == {"publisher": 1, "subscriber": 1, "service": 1, "service_client": 1}
    assert reg.lookup_fingerprint(FP["bob"]) is None


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda r: r.add_manager("alice", FP["bob"]), "already exists"),
        (lambda r: r.add_manager("bob", FP["alice"]), "already bound"),
        (lambda r: r.add_manager("9lives", FP["bob"]), "invalid manager name"),
        (lambda r: r.add_manager("bob", "xyz"), "invalid certificate fingerprint"),
        (lambda r: r.grant("nobody", "publish", "/n", "/t", "std_msgs/String"), "unknown manager"),
        (lambda r: r.grant("alice", "publish", "/n", "chatter", "std_msgs/String"), "invalid topic"),
        (lambda r: r.grant("alice", "publish", "/n", "/chat ter", "std_msgs/String"), "invalid topic"),
        (lambda r: r.grant("alice", "publish", "talker", "/t", "std_msgs/String"), "invalid node name"),
        (lambda r: r.grant("alice", "publish", "/n", "/t", "String"), "invalid data type"),
        (lambda r: r.grant("alice", "publish", "/n", "/t", "std_msgs/String/x"), "invalid data type"),
        (lambda r: r.grant("alice", "fly", "/n", "/t", "std_msgs/String"), "invalid action"),
        (lambda r: r.revoke("alice", "publish", "/n", "/never", None), "has no publish grant"),
        (lambda r: r.set_enabled("nobody", False), "unknown manager"),
        (lambda r: r.set_cert("alice", FP["carol"]), "already bound"),
        (lambda r: r.revoke_token("not a jti!"), "invalid token id"),
        (lambda r: r.revoke_token(new_jti()), "unknown token id"),
    ],
)
def test_bad_input_is_refused_and_changes_nothing(reg, call, message):
    reg.add_manager("alice", FP["alice"])
    reg.add_manager("carol", FP["carol"])
    reg.grant("alice", "publish", "/talker", "/chatter", "std_msgs/String")
    before = snapshot(reg), reg.revocation_feed(now=time.time())
    with pytest.raises(RegistryError, match=message):
        call(reg)
    assert (snapshot(reg), reg.revocation_feed(now=time.time())) == before


def _issue(reg: Registry, manager: str, *, lifetime: int = 300, kid: str = "k1") -> str:
    jti = new_jti()
    reg.record([AuditEntry("issued", manager, FP.get(manager), "127.0.0.1", "", jti, kid,
                           int(time.time()) + lifetime)])
    return jti


def test_taking_rights_away_revokes_live_tokens_of_that_manager_only(reg):
    for n in ("alice", "bob"):
        reg.add_manager(n, FP[n])
        reg.grant(n, "publish", "/talker", "/chatter", "std_msgs/String")
    live, expired, other = _issue(reg, "alice"), _issue(reg, "alice", lifetime=-10), _issue(reg, "bob")
    serial0 = reg.revocation_feed(now=time.time()).serial
    assert reg.revoke("alice", "publish", "/talker", "/chatter") == 1
    feed = reg.revocation_feed(now=time.time())
    assert live in feed.revoked_jtis and other not in feed.revoked_jtis and expired not in feed.revoked_jtis
    assert feed.serial > serial0
    reg.set_enabled("bob", False)
    feed = reg.revocation_feed(now=time.time())
    assert other in feed.revoked_jtis and feed.disabled_managers == ("bob",)
    # revoked ids drop out of the feed once the token would have expired anyway
    assert live not in reg.revocation_feed(now=time.time() + 400).revoked_jtis


def test_a_renewal_with_an_overlap_accepts_both_certificates_for_its_time_and_revokes_nothing(reg):
    """``set-cert --overlap``: the old certificate still resolves to the manager (the
    daemon's lookup) until the overlap ends, no token is revoked; without an overlap the
    old one is refused at once and the manager's tokens are revoked; a certificate
    accepted as another manager's previous one is not free."""
    new = "e" * 64
    reg.add_manager("alice", FP["alice"])
    reg.add_manager("bob", FP["bob"])
    reg.grant("alice", "publish", "/talker", "/chatter", "std_msgs/String")
    live = _issue(reg, "alice")
    version0 = reg.revocation_feed(now=time.time()).registry_version
    assert reg.set_cert("alice", new, overlap=600) == 0
    now = time.time()
    feed = reg.revocation_feed(now=now)
    assert live not in feed.revoked_jtis and feed.registry_version > version0  # replicas re-read the manager
    for fp in (FP["alice"], new):
        info = reg.lookup_fingerprint(fp, now=now)
        assert info is not None and info.name == "alice" and len(info.grants) == 1
    assert reg.lookup_fingerprint(FP["alice"], now=now + 601) is None  # the overlap is over
    assert reg.lookup_fingerprint(new, now=now + 601).name == "alice"
    shown = reg.get_manager("alice")
    assert shown.fingerprint == new and shown.previous_fingerprint == FP["alice"]
    with pytest.raises(RegistryError, match="already bound"):
        reg.set_cert("bob", FP["alice"])  # still alice's while the overlap lasts
    with pytest.raises(RegistryError, match="overlap"):
        reg.set_cert("alice", "f" * 64, overlap=10 ** 6)
    # ending the overlap early: set-cert again with the same certificate and no overlap
    assert reg.set_cert("alice", new) == 1
    assert reg.lookup_fingerprint(FP["alice"], now=time.time()) is None
    assert live in reg.revocation_feed(now=time.time()).revoked_jtis
    assert reg.get_manager("alice").previous_fingerprint is None


def test_revoke_token_uses_the_expiry_from_the_audit_log(reg):
    reg.add_manager("alice", FP["alice"])
    jti = _issue(reg, "alice", lifetime=120)
    assert reg.revoke_token(jti) is True and reg.revoke_token(jti) is False
    assert jti in reg.revocation_feed(now=time.time()).revoked_jtis
    assert jti not in reg.revocation_feed(now=time.time() + 121).revoked_jtis
    # a token the audit log never saw, with an explicit expiry
    assert reg.revoke_token("external-token-1", expires_at=int(time.time()) + 60)


def test_policy_export_import_round_trip_and_replace(reg, tmp_path):
    reg.add_manager("alice", FP["alice"])
    reg.add_manager("bob", FP["bob"], enabled=False)
    reg.grant("alice", "publish", "/talker", "/chatter", "std_msgs/String")
    reg.grant("alice", "serve", "/adder", "/add_two_ints", "rospy_tutorials/AddTwoInts")
    reg.grant("bob", "subscribe", "*", "/scan", "sensor_msgs/LaserScan")
    policy = reg.export_policy()
    # into an empty registry: identical policy
    engine = dbmod.open_registry(f"sqlite:///{tmp_path / 'copy.db'}", create=True)
    try:
        Registry(engine).import_policy(policy)
        assert Registry(engine).export_policy() == policy
    finally:
        engine.dispose()
    # replace: carol appears, bob goes, alice loses a grant and gains one
    jti = _issue(reg, "alice")
    new = {"version": 1, "managers": [
        {"name": "alice", "fingerprint_sha256": FP["alice"], "enabled": True, "grants": {
            "publish": [{"node": "/talker", "topic": "/chatter", "type": "std_msgs/String"}],
            "call": [{"node": "/c", "service": "/s", "type": "pkg/srv/S"}]}},
        {"name": "carol", "fingerprint_sha256": FP["carol"], "enabled": True},
    ]}
    stats = reg.import_policy(new)
    assert stats["managers_added"] == 1 and stats["managers_removed"] == 1
    assert stats["grants_added"] == 1 and stats["grants_removed"] == 1 and stats["tokens_revoked"] == 1
    assert [m["name"] for m in reg.export_policy()["managers"]] == ["alice", "carol"]
    assert jti in reg.revocation_feed(now=time.time()).revoked_jtis
    assert reg.import_policy(new) == dict.fromkeys(stats, 0)  # idempotent


def test_import_swapping_certificates_between_managers(reg):
    reg.add_manager("alice", FP["alice"])
    reg.add_manager("bob", FP["bob"])
    policy = reg.export_policy()
    policy["managers"][0]["fingerprint_sha256"], policy["managers"][1]["fingerprint_sha256"] = FP["bob"], FP["alice"]
    reg.import_policy(policy)
    assert reg.lookup_fingerprint(FP["bob"]).name == "alice"
    assert reg.lookup_fingerprint(FP["alice"]).name == "bob"


def test_a_merge_that_does_not_say_enabled_leaves_a_disabled_manager_disabled(reg):
    """A draft merged in (from-graph, import-sros2) adds grants; it never re-enables a
    manager an operator disabled (a lost robot), nor enables one a plain import adds."""
    reg.add_manager("alice", FP["alice"])
    reg.set_enabled("alice", False)
    doc = {"version": 1, "managers": [{"name": "alice", "grants": {"publish": [
        {"node": "/talker", "topic": "/chatter", "type": "std_msgs/String"}]}}]}
    stats = reg.import_policy(doc, merge=True)
    assert stats["grants_added"] == 1
    alice = next(m for m in reg.export_policy()["managers"] if m["name"] == "alice")
    assert alice["enabled"] is False
    reg.import_policy({"version": 1, "managers": [{**doc["managers"][0], "enabled": True}]}, merge=True)
    assert next(m for m in reg.export_policy()["managers"] if m["name"] == "alice")["enabled"] is True


@pytest.mark.parametrize(
    "doc, message",
    [
        ([], "must be a mapping"),
        ({"version": 2, "managers": []}, "version must be 1"),
        ({"version": 1, "managers": [], "extra": 1}, "unknown key"),
        ({"version": 1, "managers": [{"name": "x", "fingerprint_sha256": FP["dave"], "colour": "red"}]},
         "unknown key"),
        ({"version": 1, "managers": [{"name": "x", "grants": {"publish": [
            {"node": "/a", "topic": "/ok", "type": "std_msgs/String"},
            {"node": "/a", "topic": "not/global", "type": "std_msgs/String"}]}}]}, "invalid topic"),
        ({"version": 1, "managers": [{"name": "x", "grants": {"serve": [
            {"node": "/a", "topic": "/s", "type": "pkg/srv/S"}]}}]}, "exactly the keys"),
        ({"version": 1, "managers": [{"name": "x"}, {"name": "x"}]}, "listed twice"),
        ({"version": 1, "managers": [{"name": "x", "fingerprint_sha256": FP["dave"]},
                                     {"name": "y", "fingerprint_sha256": FP["dave"]}]}, "two managers"),
        ({"version": 1, "managers": [{"name": "x", "enabled": "yes"}]}, "'enabled' must be"),
        ({"version": 1, "managers": {}}, "'managers' must be a list"),  # was read as [], removing all
        ({"version": 1, "managers": ""}, "'managers' must be a list"),
        ({"version": 1, "managers": [{"name": "alice", "grants": []}]}, "'grants' must be a mapping"),
    ],
)
def test_bad_policy_import_changes_nothing(reg, doc, message):
    reg.add_manager("alice", FP["alice"])
    reg.grant("alice", "publish", "/talker", "/chatter", "std_msgs/String")
    before = snapshot(reg)
    with pytest.raises(RegistryError, match=message):
        reg.import_policy(doc)
    assert snapshot(reg) == before


def test_key_rotation_keeps_retired_keys_published_while_their_tokens_live(reg):
    k1 = reg.rotate_key(UNSAFE)
    assert reg.active_key().kid == k1
    _issue(reg, "alice", lifetime=300, kid=k1)
    k2 = reg.rotate_key(UNSAFE)
    assert reg.active_key().kid == k2 and k1 != k2
    now = time.time()
    assert {k.kid for k in reg.published_keys(now=now, max_lifetime=360)} == {k1, k2}
    # no grace period: k1 stays only because the audit log says a token it signed is live
    assert {k.kid for k in reg.published_keys(now=now, max_lifetime=0)} == {k1, k2}
    # long after the last token signed by k1 expired and the grace period ended
    assert {k.kid for k in reg.published_keys(now=now + 3600, max_lifetime=360)} == {k2}
    assert [k.active for k in reg.list_keys()] == [False, True]
    k3 = reg.rotate_key(UNSAFE)  # k2 never signed anything: dropped at once without grace
    assert {k.kid for k in reg.published_keys(now=time.time(), max_lifetime=0)} == {k1, k3}


def test_encrypted_signing_key_needs_its_passphrase(reg):
    from authz_server.keys import load_private

    kid = reg.rotate_key(KeyProtection(passphrase=b"correct horse"))
    active = reg.active_key()
    assert active.encrypted and b"ENCRYPTED" in active.private_pem
    load_private(active.private_pem, True, KeyProtection(passphrase=b"correct horse"), kid)
    with pytest.raises(ConfigError, match="wrong passphrase"):
        load_private(active.private_pem, True, KeyProtection(passphrase=b"wrong horse"), kid)
    with pytest.raises(ConfigError, match="passphrase"):
        KeyProtection(passphrase=None)


def test_audit_log_keeps_issues_and_denials_in_order(reg):
    reg.record([AuditEntry("denied", None, FP["dave"], "127.0.0.9", "unknown_certificate")])
    jti = _issue(reg, "alice")
    rows = reg.audit(limit=10)
    assert [(r.event, r.reason) for r in rows] == [("denied", "unknown_certificate"), ("issued", "")]
    assert rows[1].jti == jti and rows[0].at <= rows[1].at <= datetime.now(UTC) + timedelta(seconds=1)
    assert [r.event for r in reg.audit(event="denied")] == ["denied"]


def test_token_ids_are_128_bit_hex_so_the_cli_never_reads_one_as_an_option():
    from authz_server.registry import new_jti

    ids = [new_jti() for _ in range(5000)]
    assert len(set(ids)) == len(ids)
    assert all(len(j) == 32 and set(j) <= set("0123456789abcdef") for j in ids), ids[:3]


def test_the_audit_log_is_bounded_by_age_and_rows_but_keeps_unexpired_tokens(reg):
    """An insider hammering /token (each issue is a row) must not grow the table without
    bound: rows past the retention and beyond the row cap go, oldest first, except rows
    of tokens still valid (the JWKS keeps a retired key while one lives)."""

    now = 1_900_000_000
    at = datetime.fromtimestamp(now, tz=UTC)
    old = [AuditEntry("issued", None, None, "127.0.0.1", "", f"old{i}", "k1", now - 3600, at - timedelta(days=100))
           for i in range(5)]
    live_old = [AuditEntry("issued", None, None, "127.0.0.1", "", "live-old", "k1", now + 300, at - timedelta(days=100))]
    recent = [AuditEntry("denied", None, None, "127.0.0.1", f"r{i}", at=at - timedelta(seconds=100 - i))
              for i in range(20)]
    reg.record(old + live_old + recent)
    assert reg.prune_audit(keep_days=90, max_rows=10, now=now) == 5 + 10  # old by age, then all but the newest 10
    left = reg.audit(limit=1000)
    assert [e.jti for e in left if e.jti] == ["live-old"]  # unexpired: kept past age and cap
    assert [e.reason for e in left if e.event == "denied"] == [f"r{i}" for i in range(10, 20)]
    assert reg.prune_audit(keep_days=90, max_rows=10, now=now) == 0
