"""The record of registry changes, through the real ``cryptoros-authz`` CLI run as
subprocesses on a real SQLite file (and a throwaway PostgreSQL cluster where the
server is installed: tests/postgres_fixture.py).

Each command that changes the registry leaves exactly one row naming who ran it and
what changed; a refused command, or one that changes nothing, leaves none; a row
edited, deleted or cut from the end of the chain is found by ``audit --verify``; two
CLIs writing at once keep one chain.
"""

from __future__ import annotations

import json
import os
import pwd
import socket
import sqlite3
import subprocess
from contextlib import closing
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from authz_server.db import make_engine
from authz_server.registry import Registry
from tests.authz_support import AuthzDaemon, authz, build_team, ok
from tests.support import script

pytest_plugins = ["tests.postgres_fixture"]

FP = {c: c * 64 for c in "abcdef"}


@pytest.fixture(params=["sqlite", "postgres"])
def db(request, tmp_path) -> str:
    """A migrated, empty registry."""
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'registry.db'}"
    else:
        url = request.getfixturevalue("postgres_url")
    ok(authz("db", "upgrade", db=url))
    return url


@pytest.fixture
def sqlite_db(tmp_path) -> str:
    url = f"sqlite:///{tmp_path / 'registry.db'}"
    ok(authz("db", "upgrade", db=url))
    return url


def changes(db: str, *extra: str) -> list[dict]:
    """The record as ``audit --changes --json`` prints it."""
    out = ok(authz("audit", "--changes", "--json", *extra, db=db))
    return [json.loads(line) for line in out.splitlines()]


def recorded(db: str) -> list[dict]:
    """The record read in this process (quicker than a CLI per step), as ``changes`` has it."""
    engine = make_engine(db)
    try:
        return [{"seq": c.seq, "at": c.at.isoformat(), "os_user": c.os_user, "host": c.host, "command": c.command,
                 "target": c.target, "before": c.before, "after": c.after, "hash": c.hash}
                for c in Registry(engine).changes()]
    finally:
        engine.dispose()


def execute(db: str, sql: str, *params) -> None:
    """Change the database behind the registry's back: sqlite3 or psycopg, directly."""
    if db.startswith("sqlite:///"):
        with closing(sqlite3.connect(db.removeprefix("sqlite:///"))) as conn:
            conn.execute(sql, params)
            conn.commit()
    else:
        import psycopg

        with psycopg.connect(db.replace("postgresql+psycopg://", "postgresql://"), connect_timeout=10) as conn:
            conn.execute(sql.replace("?", "%s"), params)


def verify(db: str) -> subprocess.CompletedProcess:
    return authz("audit", "--verify", db=db)


def broken_at(db: str) -> str:
    r = verify(db)
    assert r.returncode == 1, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


def test_each_change_leaves_one_row_with_who_and_what(db, tmp_path):
    start = datetime.now(UTC) - timedelta(seconds=1)
    pw = tmp_path / "signing.pass"
    pw.write_text("a-signing-passphrase\n")
    policy = tmp_path / "policy.yaml"
    G = "publish /talker /chatter std_msgs/String"
    # (command, target, before, after), each must add exactly this one row
    steps = [
        (["add-manager", "alice", "--fingerprint", FP["a"]], "manager alice", None,
         {"fingerprint": FP["a"], "enabled": True, "grants": [], "previous_fingerprint": None,
          "previous_until": None}),
        (["grant", "alice", "publish", "/talker", "/chatter", "std_msgs/String"], "manager alice",
         {"grants": []}, {"grants": [G]}),
        (["disable-manager", "alice"], "manager alice", {"enabled": True}, {"enabled": False}),
        (["enable-manager", "alice"], "manager alice", {"enabled": False}, {"enabled": True}),
        (["grant-tools", "alice", "--topic", "/chatter:std_msgs/String"], "manager alice",
         {"grants": []}, {"grants": ["subscribe /record_* /chatter std_msgs/String",
                                     "subscribe /rostopic_* /chatter std_msgs/String"]}),
        (["grant-tools", "alice", "--topic", "/chatter:std_msgs/String", "--remove"],
         "manager alice", {"grants": ["subscribe /record_* /chatter std_msgs/String",
                                      "subscribe /rostopic_* /chatter std_msgs/String"]}, {"grants": []}),
        (["revoke", "alice", "publish", "/talker", "/chatter"], "manager alice", {"grants": [G]}, {"grants": []}),
        (["set-cert", "alice", "--fingerprint", FP["b"]], "manager alice",
         {"fingerprint": FP["a"]}, {"fingerprint": FP["b"]}),
        (["revoke-token", "0123456789abcdef", "--expires-at", "2000000000", "--reason", "lost laptop"],
         "token 0123456789abcdef", None, {"revoked": True, "expires_at": 2000000000, "reason": "lost laptop"}),
        (["import", str(policy)], "policy",
         {"managers": {"alice": {"enabled": True}, "bob": None}},
         {"managers": {"alice": {"enabled": False}, "bob": {"fingerprint": FP["c"], "enabled": True, "grants": [G],
                                                            "previous_fingerprint": None, "previous_until": None}}}),
        (["remove-manager", "bob"], "manager bob",
         {"fingerprint": FP["c"], "enabled": True, "grants": [G], "previous_fingerprint": None,
          "previous_until": None}, None),
    ]
    policy.write_text(
        "version: 1\nmanagers:\n"
        f"- {{name: alice, fingerprint_sha256: {FP['b']}, enabled: false}}\n"
        f"- name: bob\n  fingerprint_sha256: {FP['c']}\n"
        "  grants: {publish: [{node: /talker, topic: /chatter, type: std_msgs/String}]}\n")
    for n, (args, target, before, after) in enumerate(steps, start=1):
        ok(authz(*args, db=db))
        rows = recorded(db)
        assert len(rows) == n, (args, rows)
        row = rows[-1]
        assert (row["seq"], row["target"], row["before"], row["after"]) == (n, target, before, after), args
        assert row["command"].startswith(f"cryptoros-authz {args[0]} ")
        assert db not in row["command"] and "--db" not in row["command"]  # a URL may carry a password

    # set-cert with an overlap: the old certificate stays accepted, nothing revoked
    ok(authz("set-cert", "alice", "--fingerprint", FP["d"], "--overlap", "60", db=db))
    row = recorded(db)[-1]
    assert row["before"] == {"fingerprint": FP["b"], "previous_fingerprint": None, "previous_until": None}
    assert row["after"]["fingerprint"] == FP["d"] and row["after"]["previous_fingerprint"] == FP["b"]

    # key rotation, under the new option name and the old one
    ok(authz("rotate-key", "--signing-key-passphrase-file", str(pw), db=db))
    first = recorded(db)[-1]
    assert (first["target"], first["before"]) == ("signing key", {"active": None})
    assert first["after"]["active"] and first["after"]["encrypted"] is True
    ok(authz("rotate-key", "--key-passphrase-file", str(pw), db=db))
    second = recorded(db)[-1]
    assert second["before"] == {"active": first["after"]["active"]}
    assert second["after"]["active"] != first["after"]["active"]

    rows = changes(db)
    assert rows == recorded(db) and len(rows) == len(steps) + 3
    me = pwd.getpwuid(os.geteuid()).pw_name
    for row in rows:
        assert row["os_user"].split()[0] == me and row["host"] == socket.gethostname()
        assert start <= datetime.fromisoformat(row["at"]) <= datetime.now(UTC)
    r = verify(db)
    assert r.returncode == 0 and r.stdout.startswith(f"{len(rows)} rows, chain intact"), (r.stdout, r.stderr)

    # the table lists the same rows, one line each; --since cuts the old ones
    table = ok(authz("audit", "--changes", db=db)).splitlines()
    assert len(table) == len(rows) + 1 and f"{me}" in table[1]
    assert "+grant publish /talker /chatter std_msgs/String" in table[2]
    assert changes(db, "--since", "1h") == rows
    assert changes(db, "--since", (datetime.now(UTC) + timedelta(minutes=5)).isoformat()) == []
    assert changes(db, "--limit", "2") == rows[-2:]


def test_a_refused_or_idle_command_leaves_no_row(sqlite_db, tmp_path):
    db = sqlite_db
    ok(authz("add-manager", "alice", "--fingerprint", FP["a"], db=db))
    ok(authz("add-manager", "bob", "--fingerprint", FP["b"], db=db))
    ok(authz("grant", "alice", "publish", "/talker", "/chatter", "std_msgs/String", db=db))
    pw, wrong = tmp_path / "right.pass", tmp_path / "wrong.pass"
    pw.write_text("the-right-passphrase\n")
    wrong.write_text("the-wrong-passphrase\n")
    ok(authz("rotate-key", "--signing-key-passphrase-file", str(pw), db=db))
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("version: 1\nmanagers: [{name: alice, fingerprint_sha256: nothex}]\n")
    steal = tmp_path / "steal.yaml"  # refused inside the transaction, after the lock was taken
    steal.write_text(f"version: 1\nmanagers: [{{name: carol, fingerprint_sha256: {FP['a']}}}]\n")
    before = changes(db)
    assert len(before) == 4
    refused = [
        ["grant", "nobody", "publish", "/talker", "/chatter", "std_msgs/String"],
        ["grant", "alice", "publish", "not a topic", "/chatter", "std_msgs/String"],
        ["revoke", "alice", "subscribe", "/talker", "/chatter"],
        ["add-manager", "alice", "--fingerprint", FP["c"]],
        ["add-manager", "carol", "--fingerprint", FP["b"]],
        ["set-cert", "alice", "--fingerprint", FP["b"]],
        ["disable-manager", "nobody"],
        ["remove-manager", "nobody"],
        ["grant-tools", "alice", "--topic", "/chatter:std_msgs/String", "--service", "nocolon"],
        ["import", str(bad_yaml)],
        ["import", "--merge", str(steal)],
        ["rotate-key", "--signing-key-passphrase-file", str(wrong)],
        ["revoke-token", "0123456789abcdef"],
    ]
    idle = [
        ["grant", "alice", "publish", "/talker", "/chatter", "std_msgs/String"],
        ["enable-manager", "alice"],
        ["set-cert", "alice", "--fingerprint", FP["a"]],
        ["grant-tools", "bob", "--topic", "/x:std_msgs/String", "--remove"],
    ]
    for args in refused:
        r = authz(*args, db=db)
        assert r.returncode == 2 and "Traceback" not in r.stderr, (args, r.stdout, r.stderr)
    for args in idle:
        ok(authz(*args, db=db))
    assert changes(db) == before
    assert ok(verify(db)).startswith("4 rows, chain intact")


def test_an_edited_row_is_named(db):
    for c in "abc":
        ok(authz("add-manager", f"m{c}", "--fingerprint", FP[c], db=db))
    ok(authz("disable-manager", "mb", db=db))
    assert ok(verify(db)).startswith("4 rows, chain intact")
    execute(db, "UPDATE registry_change SET after = ? WHERE seq = 2", '{"enabled":true,"fingerprint":null}')
    line = broken_at(db)
    assert "row 2:" in line and "edited" in line, line
    assert ok(authz("audit", "--changes", db=db))  # the record is still readable


def test_a_deleted_row_is_found_in_the_middle_and_at_the_end(db):
    for c in "abcd":
        ok(authz("add-manager", f"m{c}", "--fingerprint", FP[c], db=db))
    execute(db, "DELETE FROM registry_change WHERE seq = 4")
    line = broken_at(db)
    assert "4 row(s)" in line and "3 are there" in line, line  # cut from the end
    ok(authz("add-manager", "me", "--fingerprint", FP["e"], db=db))  # the next change does not hide it
    assert [r["seq"] for r in changes(db)] == [1, 2, 3, 5]
    line = broken_at(db)
    assert "row 5:" in line and "missing" in line, line
    execute(db, "DELETE FROM registry_change WHERE seq = 2")
    line = broken_at(db)
    assert "row 3:" in line and "missing" in line, line


def test_a_row_inserted_or_renumbered_is_found(sqlite_db):
    db = sqlite_db
    for c in "abc":
        ok(authz("add-manager", f"m{c}", "--fingerprint", FP[c], db=db))
    # a forged row in the middle: row 2's content under row 3's number, the real row 3 moved up
    execute(db, "UPDATE registry_change SET seq = 4 WHERE seq = 3")
    execute(db, "INSERT INTO registry_change (seq, at, os_user, host, command, target, before, after, prev_hash, hash) "
                "SELECT 3, at, os_user, host, command, 'manager mz', before, after, hash, hash "
                "FROM registry_change WHERE seq = 2")
    line = broken_at(db)
    assert "row 3:" in line, line


def test_two_clis_at_once_keep_one_chain(db, tmp_path):
    """Two shells, each running the CLI back to back (granting its own nodes), start
    together; every command succeeds and the chain holds every change once."""
    ok(authz("add-manager", "alice", "--fingerprint", FP["a"], db=db))
    per_writer = 6
    env = {k: v for k, v in os.environ.items() if not k.startswith("CRYPTOROS_AUTHZ")}
    cli = script("cryptoros-authz")
    go = tmp_path / "go"
    writers = []
    for w in ("a", "b"):
        loop = (f'while [ ! -e "{go}" ]; do sleep 0.01; done; '
                f'for i in $(seq 1 {per_writer}); do '
                f'"{cli}" --db "{db}" grant alice publish /w{w}_$i /chatter std_msgs/String || exit 1; done')
        writers.append(subprocess.Popen(["bash", "-c", loop], env=env, stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True))
    try:
        Path(go).touch()
        outs = [p.communicate(timeout=120) for p in writers]
    finally:
        for p in writers:
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, (out, err) in zip(writers, outs, strict=True):
        assert p.returncode == 0, (out, err)
        assert out.count("granted:") == per_writer
    rows = changes(db)
    assert [r["seq"] for r in rows] == list(range(1, 2 * per_writer + 2))
    granted = sorted(g for r in rows[1:] for g in r["after"]["grants"])
    assert granted == sorted(f"publish /w{w}_{i} /chatter std_msgs/String"
                             for w in "ab" for i in range(1, per_writer + 1))
    # the two writers interleaved (not one after the other): the chain still holds
    order = [r["after"]["grants"][0].split()[1][:3] for r in rows[1:]]
    assert order != sorted(order), order
    assert ok(verify(db)).startswith(f"{2 * per_writer + 1} rows, chain intact")


def test_the_old_passphrase_option_still_works_but_help_shows_the_new_one(sqlite_db, tmp_path):
    pw = tmp_path / "signing.pass"
    pw.write_text("a-signing-passphrase\n")
    for verb in ("rotate-key", "serve"):
        text = ok(authz(verb, "--help", db=sqlite_db))
        assert "--signing-key-passphrase-file" in text
        assert "--key-passphrase-file" not in text.replace("--signing-key-passphrase-file", "")
    assert "new signing key" in ok(authz("rotate-key", "--key-passphrase-file", str(pw), db=sqlite_db))
    r = authz("rotate-key", "--signing-key-passphrase-file", str(tmp_path / "missing"), db=sqlite_db)
    assert r.returncode == 2 and "missing" in r.stderr


def test_verify_refuses_other_options_and_since_is_checked(sqlite_db):
    for args in (["--verify", "--changes"], ["--changes", "--since", "yesterday"], ["--changes", "--event", "issued"]):
        r = authz("audit", *args, db=sqlite_db)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)
    assert ok(verify(sqlite_db)).startswith("0 rows, chain intact")


def test_a_registry_from_before_the_change_record_gets_it(tmp_path):
    """A registry made by the previous schema (0003) is migrated on first use: the new
    table appears, the managers stay, the next change starts the chain."""
    from authz_server import db as dbmod

    url = f"sqlite:///{tmp_path / 'old.db'}"
    engine = dbmod.make_engine(url, create=True)
    try:
        assert dbmod.upgrade(engine, "0003") == "0003"
    finally:
        engine.dispose()
    with closing(sqlite3.connect(tmp_path / "old.db")) as conn:
        conn.execute("INSERT INTO manager (name, cert_fingerprint, enabled, created_at) "
                     "VALUES ('alice', ?, 1, '2026-01-01 00:00:00')", (FP["a"],))
        conn.commit()
    ok(authz("grant", "alice", "publish", "/talker", "/chatter", "std_msgs/String", db=url))
    assert ok(authz("db", "current", db=url)).startswith(dbmod.KNOWN_HEAD)
    rows = changes(url)
    assert [(r["seq"], r["target"], r["after"]) for r in rows] == [
        (1, "manager alice", {"grants": ["publish /talker /chatter std_msgs/String"]})]
    assert ok(verify(url)).startswith("1 rows, chain intact")


def test_the_daemon_records_the_key_it_makes_and_tokens_are_not_changes(tmp_path):
    """``serve`` on a registry with no signing key makes one: a change, recorded as made
    by ``cryptoros-authz serve``; the tokens it issues are audit rows, not changes."""
    team = build_team(tmp_path)
    daemon = AuthzDaemon(pki=team.pki, db=team.db, workdir=team.workdir)
    try:
        daemon.start()
        status, _ = daemon.token("alice")
        assert status == 200
        ok(authz("disable-manager", "alice", db=team.db))  # while the daemon runs
    finally:
        daemon.stop()
    rows = changes(team.db)
    assert [(r["target"], r["command"].split()[:2]) for r in rows] == [
        ("policy", ["cryptoros-authz", "import"]), ("signing key", ["cryptoros-authz", "serve"]),
        ("manager alice", ["cryptoros-authz", "disable-manager"])]
    assert rows[1]["before"] == {"active": None} and rows[1]["after"]["encrypted"] is True
    assert "issued manager=alice" in ok(authz("audit", db=team.db))
    assert ok(verify(team.db)).startswith("3 rows, chain intact")
