"""``cryptoros-authz import`` of a hand-written policy, as an operator runs it: the CLI
as a subprocess on a real SQLite registry.

A manager the file names without ``fingerprint_sha256`` keeps its certificate; every
import and dry run names each manager and grant it changes, one line each, before the
counts; a policy of the wrong shape or not YAML at all is one error line naming the
place (``file:line:column``), exit status 2, and the registry unchanged.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.authz_support import authz, ok

FP1 = "a1" * 32
FP2 = "b2" * 32
FP3 = "c3" * 32

# the registry every test starts from: two robots bound to certificates, a base without one
START = f"""\
version: 1
managers:
- name: robot1
  fingerprint_sha256: {FP1}
  grants:
    publish:
    - {{node: /robot1/driver, topic: /robot1/scan, type: sensor_msgs/LaserScan}}
    read_param:
    - {{node: /robot1/driver, namespace: /fleet}}
- name: robot2
  fingerprint_sha256: {FP2}
  grants:
    publish:
    - {{node: /robot2/driver, topic: /robot2/scan, type: sensor_msgs/LaserScan}}
- name: base
  grants:
    subscribe:
    - {{node: /map_server, topic: /robot1/scan, type: sensor_msgs/LaserScan}}
"""

# the same policy as an operator writes it by hand (docs/policy.md): no certificates
HAND_WRITTEN = "\n".join(line for line in START.splitlines() if "fingerprint_sha256" not in line) + "\n"


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("import-template") / "registry.db"
    policy = path.with_name("start.yaml")
    policy.write_text(START)
    ok(authz("import", str(policy), db=f"sqlite:///{path}"))
    return path


@pytest.fixture
def db(template, tmp_path) -> str:
    copy = tmp_path / "registry.db"
    shutil.copyfile(template, copy)
    copy.chmod(0o600)  # as the CLI made the template: it holds the token-signing keys
    return f"sqlite:///{copy}"


def write(tmp_path: Path, text: str, name: str = "policy.yaml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def one_line_error(result) -> str:
    assert result.returncode == 2, (result.returncode, result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cryptoros-authz: error: "), result.stderr
    assert "Traceback" not in result.stderr and result.stdout == ""
    return lines[0]


def test_a_hand_written_policy_keeps_every_certificate_and_null_unbinds_one_by_name(db, tmp_path):
    """Audit: a plain import of a policy without fingerprint_sha256 keys (as the docs
    write them) unbound every certificate, saying only 'managers changed 2'."""
    before = ok(authz("export", db=db))
    out = ok(authz("import", write(tmp_path, HAND_WRITTEN), db=db))
    assert out.splitlines() == ["imported: managers added 0, managers removed 0, managers changed 0, "
                                "grants added 0, grants removed 0, tokens revoked 0"]
    assert ok(authz("export", db=db)) == before

    # an explicit null still unbinds, and says so by name, first in the dry run
    unbind = write(tmp_path, HAND_WRITTEN.replace("- name: robot2\n", "- name: robot2\n  fingerprint_sha256: null\n"))
    dry = ok(authz("import", "--dry-run", unbind, db=db)).splitlines()
    assert dry[0] == (f"would unbind the certificate of manager robot2 (was {FP2}): "
                      "it gets no token until 'cryptoros-authz set-cert'")
    assert dry[1].startswith("would import (dry run, nothing changed): managers added 0, managers removed 0, "
                             "managers changed 1,") and len(dry) == 2
    assert ok(authz("export", db=db)) == before
    done = ok(authz("import", unbind, db=db)).splitlines()
    assert done[0] == dry[0].replace("would unbind", "unbound") and done[1].startswith("imported: ")
    managers = {m["name"]: m["fingerprint_sha256"] for m in _exported(db)["managers"]}
    assert managers == {"robot1": FP1, "robot2": None, "base": None}


def test_a_certificate_a_manager_keeps_cannot_be_bound_to_another(db, tmp_path):
    before = ok(authz("export", db=db))
    # base takes robot1's certificate, while robot1 (no key) keeps it
    clash = write(tmp_path, HAND_WRITTEN.replace("- name: base\n", f"- name: base\n  fingerprint_sha256: {FP1}\n"))
    for mode in ((), ("--merge",)):
        line = one_line_error(authz("import", *mode, clash, db=db))
        assert "binds one certificate to managers 'robot1' and 'base'" in line, line
        assert "'robot1' keeps its own: the file gives it no fingerprint_sha256" in line, line
    assert ok(authz("export", db=db)) == before


def test_a_merge_binding_a_kept_certificate_names_both_managers(db, tmp_path):
    """Newcomer audit: the refusal said only 'to another manager'."""
    before = ok(authz("export", db=db))
    steal = write(tmp_path, f"version: 1\nmanagers:\n- {{name: base, fingerprint_sha256: {FP1}}}\n", "steal.yaml")
    line = one_line_error(authz("import", "--merge", steal, db=db))
    assert "the certificate of manager 'robot1' to manager 'base' too" in line, line
    assert ok(authz("export", db=db)) == before


def test_a_new_managers_did_you_mean_says_the_import_removes_the_one_it_names(db, tmp_path):
    """Newcomer audit: a plain import that renames robot1 to robto1 suggested robot1
    as if it stayed; a policy audit: renaming robot2 to robot22 suggested robot1, not the
    robot2 one letter away, which the import removes."""
    renamed = write(tmp_path, HAND_WRITTEN.replace("- name: robot1\n", "- name: robto1\n"), "renamed.yaml")
    result = authz("import", "--dry-run", renamed, db=db)
    assert result.returncode == 0 and "robto1 has no certificate" in result.stderr, result.stderr
    assert "(did you mean robot1, which this dry run would remove with its certificate?)" in result.stderr, \
        result.stderr
    renamed = write(tmp_path, HAND_WRITTEN.replace("- name: robot2\n", "- name: robot22\n"), "renamed2.yaml")
    result = authz("import", "--dry-run", renamed, db=db)
    assert "(did you mean robot2, which this dry run would remove" in result.stderr, result.stderr


SHAPES = {
    # audit: these three raised TypeError in the CLI before the policy was checked
    "truncated": ("version: 1\nmanagers:\n", "'managers' must be a list, got nothing (null)"),
    "null managers": ("version: 1\nmanagers: null\n", "'managers' must be a list, got nothing (null)"),
    "int managers": ("version: 1\nmanagers: 5\n", "'managers' must be a list, got a number (5)"),
    # the same file cut after its first line would remove every manager
    "no managers": ("version: 1\n", "'managers' must be a list, got no 'managers' key"),
    "string managers": ("version: 1\nmanagers: robot1\n", "'managers' must be a list, got a string ('robot1')"),
    "mapping managers": ("version: 1\nmanagers: {robot1: {}}\n", "'managers' must be a list, got a mapping"),
    "empty file": ("", "policy must be a mapping"),
    "list file": ("- version: 1\n", "policy must be a mapping"),
    "float version": ("version: 1.0\nmanagers: []\n", "version must be 1, got 1.0"),
    "bool version": ("version: true\nmanagers: []\n", "version must be 1, got True"),
    "null version": ("version:\nmanagers: []\n", "version must be 1, got None"),
    "null manager": ("version: 1\nmanagers:\n-\n", "managers[0] must be a mapping"),
    "int name": ("version: 1\nmanagers:\n- name: 5\n", "invalid manager name 5"),
    "list fingerprint": ("version: 1\nmanagers:\n- {name: robot1, fingerprint_sha256: [a]}\n",
                         "invalid certificate fingerprint"),
    "int grants": ("version: 1\nmanagers:\n- {name: robot1, grants: 5}\n", "'grants' must be a mapping"),
    "list grants": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n  - publish: []\n",
                    "'grants' must be a mapping"),
    "null grant list": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    publish:\n",
                        "grants.publish must be a list"),
    "mapping grant list": ("version: 1\nmanagers:\n- name: robot1\n  grants: {publish: {node: /a}}\n",
                           "grants.publish must be a list"),
    "null grant": ("version: 1\nmanagers:\n- name: robot1\n  grants: {publish: [null]}\n",
                   "managers[0] (robot1): grants.publish[0] is nothing (null), not a mapping (a publish grant has "
                   "exactly the keys node, topic, type)"),
    # policy audit: a missing type, a typo and an extra key all read the same, naming none
    "missing type": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    publish:\n"
                     "    - {node: /a, topic: /t}\n", "grants.publish[0] lacks 'type' (a publish grant"),
    "key typo": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    subscribe:\n"
                 "    - {node: /a, topc: /t, type: std_msgs/String}\n",
                 "grants.subscribe[0] lacks 'topic' and has the unknown key(s) 'topc'"),
    "list node": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    publish:\n"
                  "    - {node: [/a], topic: /t, type: std_msgs/String}\n", "invalid node name"),
    "relative topic": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    publish:\n"
                       "    - {node: /a, topic: cmd_vel, type: std_msgs/String}\n",
                       "managers[0] (robot1): grants.publish[0]: invalid topic"),
}


@pytest.mark.parametrize("shape", SHAPES)
def test_a_policy_of_the_wrong_shape_is_one_line_and_changes_nothing(db, tmp_path, shape):
    text, message = SHAPES[shape]
    before = ok(authz("export", db=db))
    policy = write(tmp_path, text)
    # a plain import is the one that removes what the file leaves out; the three shapes
    # the audit found raising a traceback are tried with --merge too
    modes = ((), ("--merge",)) if shape in ("truncated", "null managers", "int managers") else ((),)
    for mode in modes:
        line = one_line_error(authz("import", *mode, policy, db=db))
        assert message in line, (mode, line)
    assert ok(authz("export", db=db)) == before


def test_a_merge_names_the_manager_it_adds_and_warns_it_has_no_certificate(db, tmp_path):
    """Audit: a misspelled manager in 'import --merge' became a new manager without a
    certificate, and the output said only 'managers added 1'."""
    typo = write(tmp_path, "version: 1\nmanagers:\n- name: robto1\n  grants:\n    publish:\n"
                           "    - {node: /robot1/lidar2, topic: /robot1/scan2, type: sensor_msgs/LaserScan}\n")
    result = authz("import", "--merge", typo, db=db)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [
        "added manager robto1 (no certificate)",
        "added grant robto1 publish /robot1/lidar2 /robot1/scan2 sensor_msgs/LaserScan",
        "imported: managers added 1, managers removed 0, managers changed 0, grants added 1, grants removed 0, "
        "tokens revoked 0",
    ]
    assert result.stderr.splitlines() == [
        "cryptoros-authz: warning: manager robto1 has no certificate: its grants reach nobody until "
        "'cryptoros-authz set-cert robto1 --cert FILE' (did you mean robot1?)"]
    # a manager added with its certificate is named, with no warning
    bound = write(tmp_path, f"version: 1\nmanagers:\n- {{name: robot3, fingerprint_sha256: {FP3}}}\n", "bound.yaml")
    result = authz("import", "--merge", bound, db=db)
    assert result.stdout.splitlines()[0] == "added manager robot3" and result.stderr == ""


def test_a_dry_run_lists_every_change_an_import_then_makes(db, tmp_path):
    """Review before applying: each manager added, removed, rebound, disabled, and each
    grant added or removed, one line each; the import prints the same in the past tense."""
    before = ok(authz("export", db=db))
    policy = write(tmp_path, f"""\
version: 1
managers:
- name: robot1
  fingerprint_sha256: {FP3}
  enabled: false
  grants:
    publish:
    - {{node: /robot1/driver, topic: /robot1/scan, type: sensor_msgs/LaserScan}}
    - {{node: /robot1/driver, topic: /robot1/odom, type: nav_msgs/Odometry}}
- name: base
- name: robot4
  fingerprint_sha256: {FP2}
""")
    dry = ok(authz("import", "--dry-run", policy, db=db)).splitlines()
    assert dry == [
        "would add manager robot4",
        "would remove manager robot2",
        f"would change the certificate of manager robot1 from {FP1} to {FP3}",
        "would disable manager robot1",
        "would add grant robot1 publish /robot1/driver /robot1/odom nav_msgs/Odometry",
        "would remove grant robot1 read_param /robot1/driver /fleet",
        "would remove grant base subscribe /map_server /robot1/scan sensor_msgs/LaserScan",
        "would import (dry run, nothing changed): managers added 1, managers removed 1, managers changed 1, "
        "grants added 1, grants removed 2, tokens revoked 0; managers removed: robot2",
    ]
    assert ok(authz("export", db=db)) == before
    done = ok(authz("import", policy, db=db)).splitlines()
    assert done[:-1] == [line.replace("would add", "added").replace("would remove", "removed")
                         .replace("would change", "changed").replace("would disable", "disabled")
                         for line in dry[:-1]]
    assert done[-1].startswith("imported: managers added 1, managers removed 1, managers changed 1,")


def test_a_large_change_lists_the_first_grants_and_counts_the_rest(db, tmp_path):
    rows = "".join(f"    - {{node: /robot1/driver, topic: /t{i:03}, type: std_msgs/String}}\n" for i in range(205))
    policy = write(tmp_path, f"version: 1\nmanagers:\n- name: robot1\n  grants:\n    publish:\n{rows}")
    lines = ok(authz("import", "--merge", "--dry-run", policy, db=db)).splitlines()
    assert len(lines) == 202 and lines[0] == "would add grant robot1 publish /robot1/driver /t000 std_msgs/String"
    assert lines[-2] == "... and 5 more grant change(s) not listed (5 added, 0 removed; --all lists them)"
    every = ok(authz("import", "--merge", "--dry-run", "--all", policy, db=db)).splitlines()
    assert len(every) == 206 and every[204] == "would add grant robot1 publish /robot1/driver /t204 std_msgs/String"


YAML_ERRORS = {
    "tab": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n\tpublish: []\n",
            "{f}:5:1: policy file is not valid YAML: found character '\\t' that cannot start any token "
            "(YAML indents with spaces, not tabs)"),
    "unquoted star": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    subscribe:\n"
                      "    - {{node: *, topic: /map, type: nav_msgs/OccupancyGrid}}\n",
                      "{f}:6:14: policy file is not valid YAML: a value starting with '*' is a YAML alias: "
                      "quote it ('*', '/robot_a/*')"),
    "unclosed brace": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    publish:\n"
                       "    - {{node: /a, topic: /t, type: std_msgs/String\n",
                       "{f}:7:1: policy file is not valid YAML: expected ',' or '}}', but got '<stream end>' "
                       "(while parsing a flow mapping started at line 6, column 7)"),
    "control character": ("version: 1\nmanagers: [\x07]\n",
                          "{f}:2:12: policy file is not valid YAML: character '\\x07' is not allowed in YAML"),
}


@pytest.mark.parametrize("text, message", YAML_ERRORS.values(), ids=YAML_ERRORS.keys())
def test_a_yaml_error_names_the_file_line_column_and_problem(db, tmp_path, text, message):
    """Audit: the message was only PyYAML's first line ('while scanning for the next token')."""
    before = ok(authz("export", db=db))
    policy = write(tmp_path, text.replace("{{", "{").replace("}}", "}"))
    line = one_line_error(authz("import", policy, db=db))
    assert line == "cryptoros-authz: error: " + message.format(f=policy), line
    assert ok(authz("export", db=db)) == before


def _exported(db: str) -> dict:
    import yaml

    return yaml.safe_load(ok(authz("export", db=db)))
