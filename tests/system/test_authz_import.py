"""``cryptoros-authz import`` of a hand-written policy, as an operator runs it: the CLI
as a subprocess on a real SQLite registry.

A policy that is not YAML is one error line naming the place (``file:line:column``),
exit status 2, and the registry unchanged.
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
