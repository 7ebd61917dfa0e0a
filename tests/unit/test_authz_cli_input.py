"""``cryptoros-authz`` input in process (click's CliRunner, SQLite in a temporary
directory, no daemon): a policy with a key given twice is refused whole, and which
registry ``serve`` opens when ``--db``, ``CRYPTOROS_AUTHZ_DB`` and the configuration
file's ``db`` disagree."""

from __future__ import annotations

import os

import pytest
from click.testing import CliRunner

import authz_server.cli as cli
import authz_server.server as server
from authz_server.db import shown_db
from cryptoros.errors import ConfigError

POLICY = """\
version: 1
managers:
  - name: robot_a
    grants:
      subscribe:
        - {node: /listener, topic: /chatter, type: std_msgs/String}
      publish:
        - {node: /talker, topic: /chatter, type: std_msgs/String}
"""


def run(*args: str, env: dict | None = None):
    return CliRunner().invoke(cli.main, list(args), env={"CRYPTOROS_AUTHZ_DB": None, **(env or {})})


def exported(db: str) -> str:
    result = run("--db", db, "export")
    assert result.exit_code == 0, result.output
    return result.stdout


@pytest.mark.parametrize(("text", "key", "line"), [
    (POLICY + "      subscribe:\n        - {node: /other, topic: /scan, type: sensor_msgs/LaserScan}\n",
     "subscribe", 9),
    (POLICY.replace("    grants:\n", "    grants: {}\n    grants:\n"), "grants", 5),
    (POLICY + "version: 1\n", "version", 9),
    (POLICY.replace("topic: /chatter, type", "topic: /chatter, topic: /scan, type", 1), "topic", 6),
])
def test_a_policy_with_a_key_given_twice_is_refused_and_the_registry_unchanged(tmp_path, text, key, line):
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    (tmp_path / "good.yaml").write_text(POLICY)
    assert run("--db", db, "import", str(tmp_path / "good.yaml")).exit_code == 0
    before = exported(db)
    (tmp_path / "twice.yaml").write_text(text)
    result = run("--db", db, "import", str(tmp_path / "twice.yaml"))
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cryptoros-authz: error: "), lines
    assert f"duplicate key {key!r} at line {line}" in lines[0] and "twice.yaml" in lines[0], lines
    assert exported(db) == before


def test_a_dry_run_import_says_what_it_would_remove_and_changes_nothing(tmp_path):
    """Day-2 audit: a plain import of a one-robot draft removed every other manager
    (the draft's header said to import it). ``--dry-run`` says so first, naming them,
    and the import itself names what it removed."""
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    both = POLICY + "  - name: robot_b\n"
    (tmp_path / "both.yaml").write_text(both)
    assert run("--db", db, "import", str(tmp_path / "both.yaml")).exit_code == 0
    before = exported(db)
    (tmp_path / "one.yaml").write_text(POLICY)
    dry = run("--db", db, "import", "--dry-run", str(tmp_path / "one.yaml"))
    assert dry.exit_code == 0, dry.output
    assert dry.stdout.splitlines() == [
        "would remove manager robot_b",
        "would import (dry run, nothing changed): managers added 0, managers removed 1, managers changed 0, "
        "grants added 0, grants removed 0, tokens revoked 0; managers removed: robot_b"]
    assert exported(db) == before
    merged = run("--db", db, "import", "--merge", "--dry-run", str(tmp_path / "one.yaml"))
    assert "managers removed 0" in merged.stdout and "managers removed:" not in merged.stdout
    done = run("--db", db, "import", str(tmp_path / "one.yaml"))
    assert done.stdout.startswith("removed manager robot_b\nimported: ") and "managers removed: robot_b" in done.stdout
    assert "robot_b" not in exported(db)


def test_an_sros2_types_file_with_a_name_given_twice_is_refused(tmp_path):
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    (tmp_path / "good.yaml").write_text(POLICY)
    assert run("--db", db, "import", str(tmp_path / "good.yaml")).exit_code == 0
    types = tmp_path / "types.yaml"
    types.write_text("/chatter: std_msgs/msg/String\n/chatter: std_msgs/msg/Int32\n")
    (tmp_path / "policy.xml").write_text("<policy version='0.2.0'><enclaves/></policy>")
    result = run("--db", db, "import-sros2", str(tmp_path / "policy.xml"),
                 "--manager-map", "/a=robot_a", "--types", str(types), "--dry-run")
    assert result.exit_code == 2, result.output
    assert "duplicate key '/chatter' at line 2 (first at line 1)" in result.stderr, result.stderr


# ---------------------------------------------------------------------- serve: which registry
FILE_DB = "sqlite:////srv/file.db"
ENV_DB = "postgresql+psycopg://authz:s3cret@db.lan/cryptoros"
FLAG_DB = "sqlite:////srv/flag.db"


@pytest.mark.parametrize(("flag", "env", "file", "chosen"), [
    (FLAG_DB, ENV_DB, FILE_DB, FLAG_DB),  # a flag wins over both
    (None, FILE_DB, FILE_DB, FILE_DB),    # both name the same one
    (None, None, FILE_DB, FILE_DB),
    (None, ENV_DB, None, ENV_DB),
    (None, None, None, cli.DEFAULT_DB_URL),
    (None, f"sqlite:///{os.getcwd()}/registry.db", "sqlite:///registry.db", "sqlite:///registry.db"),  # one file
])
def test_serve_opens_the_flags_registry_else_the_one_file_and_environment_agree_on(flag, env, file, chosen):
    assert cli.serve_db(flag=flag, env=env, file=file, config_file="authz.toml")[0] == chosen


def test_serve_refuses_a_file_and_an_environment_naming_two_registries():
    with pytest.raises(ConfigError) as info:
        cli.serve_db(flag=None, env=ENV_DB, file=FILE_DB, config_file="authz.toml")
    message = str(info.value)
    assert FILE_DB in message and "authz.toml" in message and "CRYPTOROS_AUTHZ_DB" in message
    assert "s3cret" not in message and "authz:***@db.lan" in message


@pytest.fixture
def served(monkeypatch):
    """What ``serve`` would serve (its configuration), without serving."""
    seen = []

    async def fake_serve(cfg, *args, **kwargs):
        seen.append(cfg)

    monkeypatch.setattr(server, "serve", fake_serve)
    return seen


def serve(tmp_path, *args: str, db: str | None = FILE_DB, env: dict | None = None):
    config = tmp_path / "authz.toml"
    for name in ("ca.crt", "a.crt", "a.key"):  # read by the server when it starts, not here
        (tmp_path / name).touch()
    config.write_text((f'db = "{db}"\n' if db else "")
                      + "".join(f'{key} = "{tmp_path / name}"\n' for key, name in
                                (("ca", "ca.crt"), ("cert", "a.crt"), ("key", "a.key"))))
    return run(*args, "serve", "--config", str(config), "--unsafe-no-passphrase", env=env)


def test_serve_with_the_environment_naming_another_registry_than_its_file_refuses_to_start(tmp_path, served):
    result = serve(tmp_path, env={"CRYPTOROS_AUTHZ_DB": ENV_DB})
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "two registry databases" in lines[0] and FILE_DB in lines[0], lines
    assert "s3cret" not in result.output
    assert served == []


def test_serve_takes_the_db_flag_over_the_environment_and_the_file(tmp_path, served):
    result = serve(tmp_path, "--db", ENV_DB, env={"CRYPTOROS_AUTHZ_DB": "sqlite:////srv/other.db"})
    assert result.exit_code == 0, result.output
    assert [cfg.db_url for cfg in served] == [ENV_DB]
    assert shown_db(ENV_DB) == "postgresql+psycopg://authz:***@db.lan/cryptoros"  # as "serving on ..." names it


def test_serve_takes_its_files_registry_when_the_environment_agrees_or_is_unset(tmp_path, served):
    assert serve(tmp_path, env={"CRYPTOROS_AUTHZ_DB": FILE_DB}).exit_code == 0
    assert serve(tmp_path).exit_code == 0
    assert serve(tmp_path, db=None, env={"CRYPTOROS_AUTHZ_DB": ENV_DB}).exit_code == 0
    assert [cfg.db_url for cfg in served] == [FILE_DB, FILE_DB, ENV_DB]


def _certificate(pki, path, *, days_ago_expired: float | None = None, starts_in_days: float | None = None):
    """A certificate of ``pki``'s CA for manager robot_a, out of its validity period."""
    import datetime as dt

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    from cryptoros.pemfiles import load_certificate, load_private_key

    ca, ca_key = load_certificate(pki.ca_cert), load_private_key(pki.pki.ca_key_path, None)
    now = dt.datetime.now(dt.timezone.utc)
    start = now + dt.timedelta(days=starts_in_days) if starts_in_days else now - dt.timedelta(days=30)
    end = now - dt.timedelta(days=days_ago_expired) if days_ago_expired else start + dt.timedelta(days=365)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "robot_a")]))
            .issuer_name(ca.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(start).not_valid_after(end).sign(ca_key, hashes.SHA256()))
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return path


def test_a_certificate_out_of_its_validity_is_refused_for_a_manager(tmp_path, pki):
    """add-manager and set-cert with an expired (or not yet valid) certificate: one line,
    nothing changed (no token could be issued to it; a renewal given the old file)."""
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    good = pki.issue("robot_a").cert_path
    assert run("--db", db, "add-manager", "robot_a", "--cert", str(good)).exit_code == 0
    before = exported(db)
    for bad, said in ((_certificate(pki, tmp_path / "old.crt", days_ago_expired=2), "expired on"),
                      (_certificate(pki, tmp_path / "early.crt", starts_in_days=3), "is not valid before")):
        for args in (("add-manager", "robot_b", "--cert", str(bad)),
                     ("set-cert", "robot_a", "--cert", str(bad), "--overlap", "600")):
            result = run("--db", db, *args)
            lines = result.stderr.strip().splitlines()
            assert result.exit_code == 2 and len(lines) == 1 and said in lines[0], (args, result.output)
    assert exported(db) == before


@pytest.mark.parametrize("kind", ["interceptor", "manager", "master"])
def test_a_certificate_naming_another_identity_is_not_bound_to_a_manager(tmp_path, pki, kind):
    """CLI audit: add-manager m3 with robot m2's certificate (kind interceptor, as the
    runbook issues every robot's) and set-cert m1 with it answered 0: m2's holder acted as
    the other manager. Only a manager-kind certificate was checked; every client kind is."""
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    own, other = pki.issue(f"{kind}_1", kind=kind).cert_path, pki.issue(f"{kind}_2", kind=kind).cert_path
    assert run("--db", db, "add-manager", f"{kind}_1", "--cert", str(own)).exit_code == 0
    before = exported(db)
    for args in (("add-manager", f"{kind}_3", "--cert", str(other)),
                 ("set-cert", f"{kind}_1", "--cert", str(other))):
        result = run("--db", db, *args)
        lines = result.stderr.strip().splitlines()
        assert result.exit_code == 2 and len(lines) == 1, (args, result.output)
        assert f"identifies {kind} '{kind}_2', not manager '{args[1]}'" in lines[0], lines
        assert f"cryptoros-certs issue {args[1]} --kind {kind}" in lines[0], lines
    assert exported(db) == before
    assert run("--db", db, "set-cert", f"{kind}_1", "--cert", str(own)).exit_code == 0


def test_a_file_that_cannot_be_written_is_one_line_exit_2(tmp_path):
    """CLI audit: export -o into a missing directory printed a FileNotFoundError traceback."""
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    (tmp_path / "good.yaml").write_text(POLICY)
    assert run("--db", db, "import", str(tmp_path / "good.yaml")).exit_code == 0
    target = tmp_path / "no" / "such" / "x.yaml"
    result = run("--db", db, "export", "-o", str(target))
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0] == f"cryptoros-authz: error: cannot write {target}: No such file or directory", lines
    assert not target.parent.exists()


def test_a_read_only_registry_is_one_line_exit_2(tmp_path, monkeypatch):
    """CLI audit: a write to a registry file the user may not write exited 1, where every
    other registry fault the operator fixes exits 2. (Root writes any file: the connection
    is made query-only, which SQLite refuses with the same SQLITE_READONLY.)"""
    import authz_server.db as dbmod

    db = f"sqlite:///{tmp_path / 'registry.db'}"
    (tmp_path / "good.yaml").write_text(POLICY)
    assert run("--db", db, "import", str(tmp_path / "good.yaml")).exit_code == 0
    before = exported(db)
    pragmas = dbmod._sqlite_pragmas

    def read_only(dbapi_conn, record):
        pragmas(dbapi_conn, record)
        dbapi_conn.execute("PRAGMA query_only=ON")

    monkeypatch.setattr(dbmod, "_sqlite_pragmas", read_only)
    result = run("--db", db, "disable-manager", "robot_a")
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0].startswith("cryptoros-authz: error: the registry database is read-only"), lines
    assert "readonly database" in lines[0] and "nothing was changed" in lines[0], lines
    monkeypatch.undo()
    assert exported(db) == before
