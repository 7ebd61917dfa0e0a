"""cryptoros-authz as an operator uses it: the CLI and the daemon as subprocesses.

Bad input gets one line on stderr, exit status 2, and changes nothing; the daemon
refuses to start with one clear line (no traceback) when the database or a key file
is missing or the port is taken, and stops cleanly on SIGTERM. The registry also
drives a daemon on a real PostgreSQL server.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time

import pytest

from cryptoros.tokens import KeySet, verify_access_token
from tests.support import expired_certificate, free_port, script
from tests.authz_support import AuthzDaemon, authz, build_team, ok, read_pem_der

pytest_plugins = ["tests.postgres_fixture"]


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    return build_team(tmp_path_factory.mktemp("authz-cli"))


def cli(*args: str, db: str) -> subprocess.CompletedProcess:
    """The same CLI in-process (click's runner: real registry, real files), where a
    subprocess per call would cost a second each; exit status and stderr as a subprocess."""
    from click.testing import CliRunner

    from authz_server.cli import main

    res = CliRunner().invoke(main, ["--db", db, *args], env={"CRYPTOROS_AUTHZ_DB": None,
                                                             "CRYPTOROS_AUTHZ_KEY_PASSPHRASE": None})
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return subprocess.CompletedProcess(args, res.exit_code, res.stdout, res.stderr)


def one_line_error(r: subprocess.CompletedProcess, status: int = 2) -> str:
    assert r.returncode == status, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cryptoros-authz: error: "), r.stderr
    assert "Traceback" not in r.stderr
    return lines[0]


def test_bad_admin_input_is_one_line_exit_2_and_changes_nothing(team, tmp_path):
    db = team.db
    before = ok(authz("export", db=db))
    bad_policy = tmp_path / "bad.yaml"
    bad_policy.write_text("version: 1\nmanagers:\n- name: zed\n  grants:\n    publish:\n"
                          "    - {node: /a, topic: /fine, type: std_msgs/String}\n"
                          "    - {node: /a, topic: relative, type: std_msgs/String}\n")
    not_yaml = tmp_path / "broken.yaml"
    not_yaml.write_text("version: 1\nmanagers: [\n")
    latin1 = tmp_path / "latin1.yaml"
    latin1.write_bytes("# réglage\nversion: 1\nmanagers: []\n".encode("latin-1"))
    cases = {
        ("grant", "nobody", "publish", "/talker", "/chatter", "std_msgs/String"): "unknown manager 'nobody'",
        ("grant", "alice", "publish", "/talker", "chatter", "std_msgs/String"): "invalid topic 'chatter'",
        ("grant", "alice", "publish", "/talker", "/chat-ter", "std_msgs/String"): "invalid topic",
        ("grant", "alice", "subscribe", "/talker", "/chatter", "std_msgs"): "invalid data type 'std_msgs'",
        ("grant", "alice", "fly", "/talker", "/chatter", "std_msgs/String"): "'fly' is not one of",
        ("grant", "alice", "publish"): "Missing argument",
        ("revoke", "alice", "publish", "/talker", "/nothing"): "has no publish grant",
        ("disable-manager", "nobody"): "unknown manager",
        ("add-manager", "alice", "--cert", str(team.pki.pki.cert_path_for("bob"))): "identifies manager 'bob'",
        ("add-manager", "zed", "--cert", "/nonexistent.crt"): "cannot read certificate",
        ("add-manager", "zed", "--fingerprint", "abc"): "invalid certificate fingerprint",
        ("add-manager", "zed"): "needs --cert",
        ("import", str(bad_policy)): "invalid topic 'relative'",
        ("import", str(not_yaml)): "not valid YAML",
        ("import", str(latin1)): "is not UTF-8 text",
        ("revoke-token", "unknownjti123"): "unknown token id",
        ("rotate-key",): "signing keys need a passphrase",
    }
    as_subprocess = {("grant", "nobody", "publish", "/talker", "/chatter", "std_msgs/String"),
                     ("grant", "alice", "publish", "/talker", "chatter", "std_msgs/String"),
                     ("grant", "alice", "subscribe", "/talker", "/chatter", "std_msgs"),
                     ("import", str(bad_policy)), ("import", str(latin1))}
    for args, message in cases.items():
        line = one_line_error((authz if args in as_subprocess else cli)(*args, db=db))
        assert message in line, (args, line)
    assert ok(authz("export", db=db)) == before


def test_a_full_disk_during_a_registry_write_is_one_line_and_changes_nothing(team, tmp_path):
    """Day-2 audit: a grant committed on a full disk printed SQLAlchemy's 78-line traceback."""
    import shutil

    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.fail("needs root to mount a small tmpfs") if os.environ.get("CI") else pytest.skip("needs root")
    disk = tmp_path / "small"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)], check=True, timeout=30)
    try:
        registry = disk / "registry.db"
        shutil.copy(team.db.removeprefix("sqlite:///"), registry)
        db = f"sqlite:///{registry}"
        before = ok(authz("export", db=db))
        filler = disk / "filler"
        with filler.open("wb") as fh:  # the disk full but for a few pages
            while shutil.disk_usage(disk).free > 32 << 10:
                fh.write(b"\0" * min(64 << 10, shutil.disk_usage(disk).free - (32 << 10)))
                fh.flush()
        result = authz("grant", "alice", "publish", "/n", "/t", "std_msgs/String", db=db)
        filler.unlink()
        assert result.returncode in (1, 2), (result.returncode, result.stderr)
        line = one_line_error(result, result.returncode)
        assert "nothing was changed" in line or "cannot" in line, line
        assert ok(authz("export", db=db)) == before
    finally:
        subprocess.run(["umount", "-l", str(disk)], timeout=30)


def test_missing_database_is_an_error_and_is_not_created(tmp_path):
    db_file = tmp_path / "nope.db"
    line = one_line_error(authz("list-managers", db=f"sqlite:///{db_file}"))
    assert "database not found" in line and not db_file.exists()
    line = one_line_error(authz("list-managers", db=f"sqlite:///{tmp_path}/no/such/dir/r.db"))
    assert "directory does not exist" in line
    line = one_line_error(authz("list-managers", db="nosuchdialect://x"))
    assert "database URL" in line


def test_a_new_registry_file_is_readable_by_its_owner_only(tmp_path):
    """CLI audit: the registry holds the token-signing key, and a new SQLite file was made
    0644: any local user read the key (rotate-key --unsafe-no-passphrase) or could guess
    at its passphrase offline."""
    db_file = tmp_path / "registry.db"
    url = f"sqlite:///{db_file}"
    umask = os.umask(0o022)  # what a login shell has
    try:
        ok(authz("db", "upgrade", db=url))
        ok(authz("rotate-key", "--unsafe-no-passphrase", db=url))
    finally:
        os.umask(umask)
    modes = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.glob("registry.db*")}
    assert modes and set(modes.values()) == {0o600}, modes
    # one made readable by others (by hand, a restore, an older version) is made owner-only
    # again the next time a tool opens it, and the tool says so
    for p in tmp_path.glob("registry.db*"):
        p.chmod(0o644)
    r = authz("list-managers", db=url)
    assert r.returncode == 0, r.stderr
    assert "was readable or writable by other users (mode 644): made 600" in r.stderr
    modes = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.glob("registry.db*")}
    assert set(modes.values()) == {0o600}, modes


def test_a_db_path_that_is_no_registry_is_refused_and_left_unchanged(tmp_path):
    """CLI audit: --db naming a text file made it 600 and said so before 'file is not a
    database'; naming a directory made it 700. Neither is touched now, nor an SQLite
    database of another program."""
    notes = tmp_path / "notes.txt"
    notes.write_text("hello\n")
    shared = tmp_path / "shared"
    shared.mkdir()
    foreign = tmp_path / "other.db"
    import sqlite3

    with sqlite3.connect(foreign) as conn:
        conn.execute("CREATE TABLE something_else (id INTEGER PRIMARY KEY)")
    for path in (notes, shared, tmp_path, foreign):
        path.chmod(0o755 if path.is_dir() else 0o644)
    cases = {notes: "is not an SQLite database", shared: "is a directory", tmp_path: "is a directory",
             foreign: "is not a cryptoros-authz registry"}
    for path, message in cases.items():
        for args in (("list-managers",), ("db", "upgrade")):
            line = one_line_error(cli(*args, db=f"sqlite:///{path}"))
            assert message in line, (path, args, line)
        assert path.stat().st_mode & 0o777 == (0o755 if path.is_dir() else 0o644), path
    assert notes.read_text() == "hello\n" and list(shared.iterdir()) == []


def test_a_certificate_no_client_of_this_fleet_could_present_is_not_bound(team, tmp_path, monkeypatch):
    """CLI audit: set-cert with another CA's certificate answered 0 and revoked the
    robot's tokens; its real certificate was then refused and the robot locked out.
    add-manager took the CA's own certificate, a server's and a revoked one. Each is now
    refused in one line, and the registry is unchanged."""
    db = f"sqlite:///{tmp_path / 'certs.db'}"
    ok(authz("add-manager", "alice", "--cert", str(team.pki.pki.cert_path_for("alice")), db=db))
    before = ok(cli("list-managers", "--json", db=db))
    foreign = team.other_pki.pki.cert_path_for("alice")
    line = one_line_error(cli("set-cert", "alice", "--cert", str(foreign), "--ca", str(team.pki.ca_cert), db=db))
    assert "was not issued by the fleet's CA" in line
    monkeypatch.setenv("CRYPTOROS_PKI_DIR", str(team.pki.directory))  # as the runbook sets it
    line = one_line_error(cli("set-cert", "alice", "--cert", str(foreign), db=db))
    assert "was not issued by the fleet's CA" in line and str(team.pki.ca_cert) in line
    line = one_line_error(cli("add-manager", "ca_itself", "--cert", str(team.pki.ca_cert), db=db))
    assert "is a CA certificate" in line
    server = team.pki.issue("authz_srv", kind="server")
    line = one_line_error(cli("add-manager", "srv", "--cert", str(server.cert_path), db=db))
    assert "is a server certificate" in line
    line = one_line_error(cli("add-manager", "mallory", "--cert", str(team.pki.pki.cert_path_for("mallory")), db=db))
    assert "is revoked by" in line
    assert ok(cli("list-managers", "--json", db=db)) == before
    # the other fleet's own CA binds it (--ca), as an operator of that fleet would
    ok(cli("set-cert", "alice", "--cert", str(foreign), "--ca", str(team.other_pki.ca_cert), db=db))
    monkeypatch.delenv("CRYPTOROS_PKI_DIR")
    line = one_line_error(cli("add-manager", "ca_alone", "--cert", str(team.pki.ca_cert), db=db))
    assert "is a CA certificate" in line
    # re-audit: where no CA could be found, the checks were skipped without a word
    loose = tmp_path / "loose.crt"
    loose.write_bytes(team.pki.pki.cert_path_for("carol").read_bytes())
    r = cli("add-manager", "carol", "--cert", str(loose), db=db)
    assert r.returncode == 0 and "the issuer of" in r.stderr and "was not checked" in r.stderr, r
    monkeypatch.setenv("CRYPTOROS_PKI_DIR", str(tmp_path / "nonexistent"))
    line = one_line_error(cli("set-cert", "carol", "--cert", str(loose), db=db))
    assert "holds no ca.crt" in line, line
    # a CA file of several CAs: any of them
    monkeypatch.delenv("CRYPTOROS_PKI_DIR")
    both = tmp_path / "both.crt"
    both.write_bytes(team.other_pki.ca_cert.read_bytes() + team.pki.ca_cert.read_bytes())
    ok(cli("set-cert", "carol", "--cert", str(loose), "--ca", str(both), db=db))


def test_operator_workflow_with_export_import_between_registries(team, tmp_path):
    db = f"sqlite:///{tmp_path / 'ops.db'}"
    alice = team.pki.pki.cert_path_for("alice")
    assert "added manager alice" in ok(authz("add-manager", "alice", "--cert", str(alice), db=db))
    ok(cli("grant", "alice", "publish", "/talker", "/chatter", "std_msgs/String", db=db))
    ok(cli("grant", "alice", "call", "/client", "/add_two_ints", "rospy_tutorials/AddTwoInts", db=db))
    assert "alice" in ok(cli("list-managers", db=db))
    shown = ok(cli("show-manager", "alice", db=db))
    assert "/chatter" in shown and "/add_two_ints" in shown
    policy = tmp_path / "policy.yaml"
    ok(cli("export", "-o", str(policy), db=db))
    copy = f"sqlite:///{tmp_path / 'copy.db'}"
    assert "managers added 1" in ok(cli("import", str(policy), db=copy))
    assert ok(cli("export", db=copy)) == policy.read_text()
    ok(cli("revoke", "alice", "call", "/client", "/add_two_ints", db=db))
    assert "/add_two_ints" not in ok(cli("show-manager", "alice", db=db))
    # renewal: a new certificate for alice replaces the old binding
    renewed = team.pki.issue("alice-renewed")
    r = cli("set-cert", "alice", "--cert", str(renewed.cert_path), db=db)
    assert r.returncode == 2 and "identifies manager 'alice-renewed'" in r.stderr
    ok(cli("set-cert", "alice", "--fingerprint", renewed.fingerprint_sha256, db=db))
    assert renewed.fingerprint_sha256 in ok(cli("list-managers", "--json", db=db))
    ok(cli("remove-manager", "alice", db=db))
    assert "alice" not in ok(authz("list-managers", db=db))


def test_grant_tools_grants_rosparam_only_the_namespaces_named(tmp_path):
    """Policy audit: a bundle asked for one topic also granted /rosparam-* write_param /,
    so the robot's rosparam could rewrite or delete every robot's parameters."""
    db = f"sqlite:///{tmp_path / 'tools.db'}"
    ok(authz("add-manager", "base", "--fingerprint", "ab" * 32, db=db))
    out = ok(authz("grant-tools", "base", "--topic", "/map:nav_msgs/OccupancyGrid", db=db))
    assert "rosparam" not in out and "grant-tools base: 2 grant(s) added" in out, out
    shown = ok(authz("show-manager", "base", db=db))
    assert "param" not in shown and "/map" in shown, shown
    out = ok(authz("grant-tools", "base", "--param-ns", "/base", "--params-read-only", db=db))
    assert "granted: base /rosparam-* read_param /base" in out and "grant-tools base: 1 grant(s) added" in out, out
    line = one_line_error(authz("grant-tools", "base", "--params-read-only", db=db))
    assert "--params-read-only needs" in line and "--param-ns" in line, line
    assert "write_param" not in ok(authz("show-manager", "base", db=db))
    # newcomer audit: no option granted nothing with exit 0; '/' and a write left behind said nothing
    assert "nothing to grant" in one_line_error(authz("grant-tools", "base", db=db))
    everything = authz("grant-tools", "base", "--param-ns", "/", db=db)
    assert everything.returncode == 0 and everything.stderr.strip() == (
        "cryptoros-authz: warning: --param-ns / lets base's rosparam write and delete every parameter, other "
        "robots' nodes' too; name the namespace the operator needs"), everything.stderr
    kept = authz("grant-tools", "base", "--param-ns", "/", "--params-read-only", db=db)
    assert kept.returncode == 0 and ("base's rosparam may still write / (granted before): 'cryptoros-authz "
                                     "grant-tools base --param-ns / --remove' takes that away") in kept.stderr, kept.stderr


def test_a_grant_naming_nodes_another_manager_names_is_warned(tmp_path):
    """Policy audit: a grant of robot1's exact node name to robot2, and robot2's pattern
    '/robot*' over robot1's nodes, were taken in silence. Each is granted and warned, one
    line per overlap, saying who then holds the name; '*' (any node of one's own), names
    of one's own and two patterns (stock tools' anonymous names) are not."""
    db = f"sqlite:///{tmp_path / 'overlap.db'}"
    ok(authz("add-manager", "robot1", "--fingerprint", "ab" * 32, db=db))
    ok(authz("add-manager", "robot2", "--fingerprint", "cd" * 32, db=db))
    ok(authz("grant", "robot1", "publish", "/robot1/driver", "/robot1/scan", "sensor_msgs/LaserScan", db=db))
    same = authz("grant", "robot2", "publish", "/robot1/driver", "/robot2/scan", "sensor_msgs/LaserScan", db=db)
    assert same.returncode == 0 and "granted: robot2 /robot1/driver" in same.stdout, same
    assert same.stderr.strip() == ("warning: node /robot1/driver is named by robot1's grants too: whichever "
                                   "registers it first holds it, and the other's node is refused (name_taken); "
                                   "give each robot node names of its own"), same.stderr
    wide = authz("grant", "robot2", "subscribe", "/robot*", "/robot1/scan", "sensor_msgs/LaserScan", db=db)
    assert wide.returncode == 0 and wide.stderr.strip() == (
        "warning: pattern /robot* covers node /robot1/driver, which robot1's grants name exactly: robot1's node "
        "always holds that name, and a node of robot2 registered under it is dropped"), wide.stderr
    # a stock tool's pattern held by two robots: the names under it are anonymous, never
    # shared; /roslaunch is in every robot's bundle, and no node may register it
    ok(authz("grant-tools", "robot1", "--topic", "/robot1/scan:sensor_msgs/LaserScan", "--roslaunch", db=db))
    ok(authz("grant", "robot1", "subscribe", "/robot1/listener", "/chatter", "std_msgs/msg/String", db=db))
    for quiet in (("subscribe", "*", "/robot1/scan", "sensor_msgs/LaserScan"),
                  ("publish", "/robot2/driver", "/robot2/scan", "sensor_msgs/LaserScan"),
                  ("subscribe", "/rostopic_*", "/robot1/scan", "sensor_msgs/LaserScan"),
                  ("write_param", "/roslaunch", "/robot2"),
                  # ROS 2 has no master: two robots' /listener nodes both run (a ROS 2 audit)
                  ("subscribe", "/robot1/listener", "/chatter", "std_msgs/msg/String")):
        r = authz("grant", "robot2", *quiet, db=db)
        assert r.returncode == 0 and r.stderr.strip() == "", (quiet, r.stderr)


def test_a_topic_granted_with_a_second_type_is_warned_by_grant_and_import(tmp_path):
    """Policy audit: type typos (sensor_msgs/LaserScn) and a ROS 1 and a ROS 2 spelling of
    one topic's type were taken in silence; every stream of the odd type is then refused."""
    db = f"sqlite:///{tmp_path / 'types.db'}"
    ok(authz("add-manager", "robot1", "--fingerprint", "ab" * 32, db=db))
    ok(authz("add-manager", "robot2", "--fingerprint", "cd" * 32, db=db))
    ok(authz("grant", "robot1", "publish", "/lidar", "/scan", "sensor_msgs/LaserScan", db=db))
    same = authz("grant", "robot2", "subscribe", "/nav", "/scan", "sensor_msgs/LaserScan", db=db)
    assert same.returncode == 0 and same.stderr.strip() == "", same.stderr
    typo = authz("grant", "robot2", "subscribe", "/nav2", "/scan", "sensor_msgs/LaserScn", db=db)
    assert typo.returncode == 0 and typo.stderr.strip() == (
        "warning: topic /scan is granted with 2 types: sensor_msgs/LaserScan (robot1, robot2); sensor_msgs/LaserScn "
        "(robot2); it carries one, and a stream of another is refused: a typo, or a ROS 1 and a ROS 2 spelling of "
        "one type?"), typo.stderr
    policy = tmp_path / "mixed.yaml"
    policy.write_text("version: 1\nmanagers:\n- name: robot2\n  grants:\n    subscribe:\n"
                      "    - {node: /ros2_nav, topic: /map, type: nav_msgs/msg/OccupancyGrid}\n"
                      "- name: base\n  grants:\n    publish:\n"
                      "    - {node: /map_server, topic: /map, type: nav_msgs/OccupancyGrid}\n")
    mixed = authz("import", "--merge", "--dry-run", str(policy), db=db)
    assert mixed.returncode == 0, mixed.stderr
    assert ("warning: topic /map is granted with 2 types: nav_msgs/OccupancyGrid (base); "
            "nav_msgs/msg/OccupancyGrid (robot2)") in mixed.stderr, mixed.stderr


def test_nodes_overlap_is_one_node_name_two_grants_could_both_name():
    from cryptoros.grants import nodes_overlap

    assert nodes_overlap("/a/b", "/a/b") and not nodes_overlap("/a/b", "/a/c")
    assert nodes_overlap("/robot*", "/robot1/driver") and nodes_overlap("/robot1/driver", "/robot*")
    assert nodes_overlap("/robot1*", "/robot10/x") and not nodes_overlap("/robot1/*", "/robot10/x")
    assert nodes_overlap("/robot*", "/robot1/*") and not nodes_overlap("/robot1/*", "/robot2/*")
    assert not nodes_overlap("*", "/a") and not nodes_overlap("/a*", "*")


def _serve(team, *extra: str, db: str | None = None, timeout: float = 20) -> subprocess.CompletedProcess:
    server = team.pki.issue("authz", kind="server", force=True)
    (team.workdir / "signing.pass").write_text("test-signing-passphrase\n")
    args = [script("cryptoros-authz"), "--db", db or team.db, "serve", "--ca", str(team.pki.ca_cert),
            "--cert", str(server.cert_path), "--key", str(server.key_path),
            "--signing-key-passphrase-file", str(team.workdir / "signing.pass"), *extra]
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout)


def test_serve_start_up_errors_are_one_line(team, tmp_path):
    line = one_line_error(_serve(team, "--port", str(free_port()), db=f"sqlite:///{tmp_path / 'missing.db'}"))
    assert "database not found" in line
    # day-2 audit: an expired server certificate was served without a word (every interceptor refused it)
    expired, _key = expired_certificate(tmp_path, "authz")
    line = one_line_error(_serve(team, "--port", str(free_port()), "--cert", str(expired)))
    assert "expired on" in line and "renew it" in line, line
    line = one_line_error(_serve(team, "--port", str(free_port()), "--crl", str(tmp_path / "no.crl")))
    assert "not found" in line and "no.crl" in line
    # CLI audit: started on an empty, truncated or wrong CRL, the server had issued tokens
    # to revoked certificates (the CRL watcher logged it and went on without one)
    crl = team.pki.pki.write_crl()
    for name, data in (("empty.crl", b""), ("ca-not-crl.crl", team.pki.ca_cert.read_bytes()),
                       ("truncated.crl", crl.read_bytes()[:200])):
        (tmp_path / name).write_bytes(data)
        line = one_line_error(_serve(team, "--port", str(free_port()), "--crl", str(tmp_path / name)))
        assert "CRL" in line and name in line, line
    line = one_line_error(_serve(team, "--port", str(free_port()), "--ca", str(tmp_path / "no-ca.crt")))
    assert "no-ca.crt" in line
    line = one_line_error(_serve(team, "--port", str(free_port()), "--key", str(tmp_path / "no.key")))
    assert "TLS key file not found" in line
    line = one_line_error(_serve(team, "--port", str(free_port()), "--token-lifetime", "0"))
    assert "token lifetime" in line
    cfg = tmp_path / "authz.toml"
    cfg.write_text('port = 1\nbogus = "x"\n')
    line = one_line_error(_serve(team, "--config", str(cfg)))
    assert "unknown key(s) bogus" in line
    cfg.write_bytes("# réglage\nport = 1\n".encode("latin-1"))
    line = one_line_error(_serve(team, "--config", str(cfg)))
    assert "is not UTF-8 text" in line
    line = one_line_error(_serve(team, "--port", str(free_port()),
                                 db="postgresql+psycopg://postgres@127.0.0.1:1/none"))
    assert "cannot connect to the database" in line


def test_serve_restarted_on_an_older_crl_is_refused(tmp_path):
    """CLI re-audit: a running server refused an older copy of the CRL, but one restarted
    on it issued a token to a certificate revoked after it (the runbook's restart step).
    The highest CRL number applied is kept in the registry."""
    team = build_team(tmp_path / "team")  # its own: bob is revoked here
    old = tmp_path / "old.crl"
    old.write_bytes(team.pki.pki.write_crl().read_bytes())  # before the revocation
    team.pki.revoke("bob", reason="key_compromise")  # a newer CRL, bob in it
    d = AuthzDaemon(pki=team.pki, db=team.db, workdir=team.workdir)
    try:
        d.start()  # applies the newer CRL: its number is kept
        assert d.token("alice")[0] == 200
    finally:
        d.stop()
    line = one_line_error(_serve(team, "--port", str(free_port()), "--crl", str(old)))
    assert "older than the CRLs this registry's servers applied" in line, line


def test_serve_refuses_a_wrong_signing_key_passphrase(team, tmp_path):
    pw = tmp_path / "wrong.pass"
    pw.write_text("not-the-passphrase\n")
    right = tmp_path / "right.pass"
    right.write_text("test-signing-passphrase\n")
    ok(cli("rotate-key", "--signing-key-passphrase-file", str(right), db=team.db))
    line = one_line_error(_serve(team, "--port", str(free_port()), "--signing-key-passphrase-file", str(pw)))
    assert "cannot decrypt signing key" in line


def test_rotate_key_refuses_a_passphrase_that_does_not_open_the_current_key(tmp_path):
    """Day 2: rotate-key with another passphrase answered rc 0 and the next serve could
    not decrypt its signing key. It is refused, in one line, and nothing changes;
    --change-passphrase says the operator means it."""
    team = build_team(tmp_path)
    right, wrong = tmp_path / "right.pass", tmp_path / "wrong.pass"
    right.write_text("test-signing-passphrase\n")
    wrong.write_text("another-passphrase\n")
    ok(cli("rotate-key", "--signing-key-passphrase-file", str(right), db=team.db))
    keys_before = ok(cli("list-keys", db=team.db))
    line = one_line_error(cli("rotate-key", "--signing-key-passphrase-file", str(wrong), db=team.db))
    assert "does not open the current signing key" in line
    assert ok(cli("list-keys", db=team.db)) == keys_before
    ok(cli("rotate-key", "--signing-key-passphrase-file", str(right), db=team.db))  # the right one rotates
    ok(cli("rotate-key", "--signing-key-passphrase-file", str(wrong), "--change-passphrase", db=team.db))
    line = one_line_error(_serve(team, "--port", str(free_port()), "--signing-key-passphrase-file", str(right)))
    assert "cannot decrypt signing key" in line  # what --change-passphrase asks of the operator


def test_serve_on_a_taken_port_is_one_line_exit_1(team):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        line = one_line_error(_serve(team, "--port", str(port)), status=1)
    assert "address already in use" in line


def test_sigterm_stops_the_daemon_cleanly(team):
    d = AuthzDaemon(pki=team.pki, db=team.db, workdir=team.workdir)
    try:
        d.start()
        assert d.token("alice")[0] == 200
        d.proc.send_signal(signal.SIGTERM)
        assert d.proc.wait(timeout=10) == 0
    finally:
        d.stop()
    log = d.log()
    assert "shutting down" in log and "stopped" in log and "Traceback" not in log


def test_daemon_on_postgresql(team, postgres_url):
    policy = team.workdir / "policy.yaml"
    ok(authz("import", str(policy), db=postgres_url))
    assert "alice" in ok(authz("list-managers", db=postgres_url))
    d = AuthzDaemon(pki=team.pki, db=postgres_url, workdir=team.workdir)
    try:
        d.start()
        status, body = d.token("alice")
        assert status == 200
        jwks = d.get_json("/.well-known/jwks.json")
        tok = verify_access_token(body["access_token"], keys=KeySet.from_jwks(jwks), issuer="cryptoros-authz",
                                  audience="cryptoros", peer_cert_der=read_pem_der(d.cert_of("alice")[0]))
        assert tok.subject == "alice"
        assert d.token("stranger")[0] == 401
    finally:
        d.stop()
    audit = ok(authz("audit", db=postgres_url))
    assert "issued manager=alice" in audit and "reason=unknown_certificate" in audit


def test_a_held_long_poll_answers_when_the_replica_loses_its_database(team, postgres_url):
    """A long-poll held by a replica that can no longer read the registry is answered
    then (503: its client tries another replica), not at the end of its wait: the
    database is dropped (connections terminated) under a 60 s hold, and the answer comes
    within the request's 10 s socket timeout."""
    import threading

    import psycopg

    policy = team.workdir / "policy.yaml"
    ok(authz("import", str(policy), db=postgres_url))
    d = AuthzDaemon(pki=team.pki, db=postgres_url, workdir=team.workdir)
    try:
        d.start()
        cert, key = d.cert_of("alice")
        d.request("GET", "/revocations", cert=cert, key=key)
        etag = d.last_headers["ETag"]
        answer: list = []
        holder = threading.Thread(target=lambda: answer.append(d.request(
            "GET", "/revocations?wait=60", cert=cert, key=key, headers={"If-None-Match": etag})))
        holder.start()
        d.wait_polls_held(1)  # the request is held
        server, _, name = postgres_url.replace("postgresql+psycopg://", "postgresql://").rpartition("/")
        with psycopg.connect(f"{server}/postgres", autocommit=True, connect_timeout=10) as conn:
            conn.execute(f'DROP DATABASE "{name}" WITH (FORCE)')
        holder.join(timeout=30)
        assert answer and answer[0][0] == 503, answer  # not a 304 after 60 s, nor the socket's timeout
    finally:
        d.stop()


def test_serve_from_a_toml_config_with_short_tokens_and_env_passphrase(team, tmp_path):
    import json
    import os

    server = team.pki.issue("authz", kind="server", force=True)
    port = free_port()
    cfg = tmp_path / "authz.toml"
    cfg.write_text(
        f'db = "{team.db}"\nport = {port}\nca = "{team.pki.ca_cert}"\ncert = "{server.cert_path}"\n'
        f'key = "{server.key_path}"\ncrl = "{team.pki.crl}"\nissuer = "https://authz.robots.example"\n'
        'audience = "fleet-7"\ntoken_lifetime = 60\ncache_seconds = 0.5\n'
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("CRYPTOROS_AUTHZ")}
    env["CRYPTOROS_AUTHZ_KEY_PASSPHRASE"] = "test-signing-passphrase"
    log = (tmp_path / "serve.log").open("w")
    proc = subprocess.Popen([script("cryptoros-authz"), "serve", "--config", str(cfg)], env=env,
                            stdout=log, stderr=subprocess.STDOUT)
    d = AuthzDaemon(pki=team.pki, db=team.db, workdir=tmp_path, port=port)
    try:
        from tests.support import wait_for_port

        wait_for_port("127.0.0.1", port, timeout=20, proc=proc)
        deadline = time.monotonic() + 20
        while True:
            try:
                status, body = d.token("alice")
                break
            except OSError:
                assert time.monotonic() < deadline and proc.poll() is None, (tmp_path / "serve.log").read_text()
                time.sleep(0.1)
        assert status == 200
        jwks = d.get_json("/.well-known/jwks.json", name="alice")
        tok = verify_access_token(body["access_token"], keys=KeySet.from_jwks(jwks),
                                  issuer="https://authz.robots.example", audience="fleet-7",
                                  peer_cert_der=read_pem_der(d.cert_of("alice")[0]))
        assert tok.expires_at - tok.issued_at == 60 and body["expires_in"] == 60
        assert json.loads(json.dumps(tok.claims))["aud"] == "fleet-7"
    finally:
        from tests.support import stop

        stop(proc)
    assert proc.returncode == 0


def test_probe_serves_health_and_metrics_on_loopback_without_a_certificate(team):
    """Day 2: a health checker without a client certificate reads /healthz and /metrics
    on the loopback probe port, and nothing else is there; a probe off loopback is
    refused at start in one line."""
    import json
    import urllib.error
    import urllib.request

    probe = free_port()
    d = AuthzDaemon(pki=team.pki, db=team.db, workdir=team.workdir, extra=("--probe", f"127.0.0.1:{probe}"))
    try:
        d.start()
        with urllib.request.urlopen(f"http://127.0.0.1:{probe}/healthz", timeout=5) as r:
            assert json.loads(r.read())["status"] == "ok"
        with urllib.request.urlopen(f"http://127.0.0.1:{probe}/metrics", timeout=5) as r:
            assert b"cryptoros_authz" in r.read()
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(urllib.request.Request(f"http://127.0.0.1:{probe}/token", data=b"x"), timeout=5)
        assert info.value.code in (404, 405)
    finally:
        d.stop()
    line = one_line_error(_serve(team, "--port", str(free_port()), "--probe", "0.0.0.0:9103"))
    assert "loopback" in line


def test_a_client_hammering_token_gets_429_and_writes_no_audit_rows(tmp_path):
    """An insider with a valid certificate asking for tokens in a loop (each one a
    signature and an audit row) is held to token_rate per second after token_burst:
    429 slow_down, no audit row per refused request, other clients unaffected."""
    import json

    team = build_team(tmp_path)
    cfg = tmp_path / "authz.toml"
    cfg.write_text("token_rate = 0.5\ntoken_burst = 3\n")
    d = AuthzDaemon(pki=team.pki, db=team.db, workdir=tmp_path, extra=("--config", str(cfg)))
    try:
        d.start()
        answers = [d.token("alice") for _ in range(6)]
        assert [status for status, _ in answers[:3]] == [200, 200, 200]
        assert all(status == 429 and body == {"error": "slow_down"} for status, body in answers[3:]), answers
        assert d.token("bob")[0] == 200  # per certificate
        rows = [json.loads(line) for line in ok(cli("audit", "--json", "--manager", "alice", db=team.db)).splitlines()]
        assert len(rows) == 3
    finally:
        d.stop()
    assert "answered 429" in d.log()
