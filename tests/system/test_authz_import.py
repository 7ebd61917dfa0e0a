"""``cryptoros-authz import`` of a hand-written policy, as an operator runs it: the CLI
as a subprocess on a real SQLite registry.

A manager the file names without ``fingerprint_sha256`` keeps its certificate. A
policy of the wrong shape or not YAML at all is one error line naming the place
(``file:line:column``), exit status 2, and the registry unchanged.
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


def test_a_hand_written_policy_keeps_every_certificate(db, tmp_path):
    """Audit: a plain import of a policy without fingerprint_sha256 keys (as the docs
    write them) unbound every certificate, saying only 'managers changed 2'."""
    before = ok(authz("export", db=db))
    out = ok(authz("import", write(tmp_path, HAND_WRITTEN), db=db))
    assert out.splitlines() == ["imported: managers added 0, managers removed 0, managers changed 0, "
                                "grants added 0, grants removed 0, tokens revoked 0"]
    assert ok(authz("export", db=db)) == before


def test_a_certificate_a_manager_keeps_cannot_be_bound_to_another(db, tmp_path):
    before = ok(authz("export", db=db))
    # base takes robot1's certificate, while robot1 (no key) keeps it
    clash = write(tmp_path, HAND_WRITTEN.replace("- name: base\n", f"- name: base\n  fingerprint_sha256: {FP1}\n"))
    for mode in ((), ("--merge",)):
        line = one_line_error(authz("import", *mode, clash, db=db))
        assert "binds one certificate to managers 'robot1' and 'base'" in line, line
        assert "'robot1' keeps its own: the file gives it no fingerprint_sha256" in line, line
    assert ok(authz("export", db=db)) == before


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
                   "grants.publish[0] must have exactly the keys node, topic, type"),
    "list node": ("version: 1\nmanagers:\n- name: robot1\n  grants:\n    publish:\n"
                  "    - {node: [/a], topic: /t, type: std_msgs/String}\n", "invalid node name"),
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
