"""SROS2 access-control policies in and out of the registry (``import-sros2``,
``export-sros2``): the example policies below are written here from the structure
sros2 documents (its ``sros2/policy/schemas/policy.xsd``, version 0.2.0, and the
example policies under ``sros2/test/policies``); they are read into grants, written
back and read again to the same grants. What has no equivalent is reported one line
per element; bad XML or an unknown manager is one error line and the registry's bytes
do not change. The CLI runs in-process (click's runner) on a real SQLite registry.
"""

from __future__ import annotations

import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from authz_server.graph_policy import ManagerMap
from authz_server.registry import GrantRow
from authz_server.sros2 import grants_from_sros2, resolve, sros2_from_grants
from cryptoros.errors import RegistryError

FP_A = "a" * 64
FP_B = "b" * 64

#: Everything here has a cryptoros equivalent: it must come back from export unchanged.
TEAM = """\
<?xml version="1.0" encoding="UTF-8"?>
<policy version="0.2.0">
  <enclaves>
    <enclave path="/team/robot_a">
      <profiles>
        <profile ns="/" node="talker">
          <topics publish="ALLOW">
            <topic>chatter</topic>
          </topics>
        </profile>
        <profile ns="/robot_a" node="mapper">
          <topics publish="ALLOW" subscribe="ALLOW">
            <topic>map</topic>
          </topics>
          <topics subscribe="ALLOW">
            <topic>/scan</topic>
          </topics>
          <services reply="ALLOW">
            <service>/add_two_ints</service>
            <service>~/reset</service>
          </services>
        </profile>
      </profiles>
    </enclave>
    <enclave path="/team/robot_b">
      <profiles>
        <profile ns="/" node="listener">
          <topics subscribe="ALLOW">
            <topic>chatter</topic>
          </topics>
          <services request="ALLOW">
            <service>add_two_ints</service>
          </services>
        </profile>
        <profile ns="/robot_b" node="*">
          <topics subscribe="ALLOW">
            <topic>/robot_a/map</topic>
          </topics>
        </profile>
      </profiles>
    </enclave>
  </enclaves>
</policy>
"""

TEAM_TYPES = {
    "/chatter": "std_msgs/msg/String",
    "/robot_a/map": "nav_msgs/msg/OccupancyGrid",
    "/scan": "sensor_msgs/msg/LaserScan",
    "/add_two_ints": "example_interfaces/srv/AddTwoInts",
    "/robot_a/mapper/reset": "std_srvs/srv/Empty",
}

TEAM_GRANTS = {
    "robot_a": {
        GrantRow("publish", "/talker", "/chatter", "std_msgs/msg/String"),
        GrantRow("publish", "/robot_a/mapper", "/robot_a/map", "nav_msgs/msg/OccupancyGrid"),
        GrantRow("subscribe", "/robot_a/mapper", "/robot_a/map", "nav_msgs/msg/OccupancyGrid"),
        GrantRow("subscribe", "/robot_a/mapper", "/scan", "sensor_msgs/msg/LaserScan"),
        GrantRow("serve", "/robot_a/mapper", "/add_two_ints", "example_interfaces/srv/AddTwoInts"),
        GrantRow("serve", "/robot_a/mapper", "/robot_a/mapper/reset", "std_srvs/srv/Empty"),
    },
    "robot_b": {
        GrantRow("subscribe", "/listener", "/chatter", "std_msgs/msg/String"),
        GrantRow("call", "/listener", "/add_two_ints", "example_interfaces/srv/AddTwoInts"),
        GrantRow("subscribe", "/robot_b/*", "/robot_a/map", "nav_msgs/msg/OccupancyGrid"),
    },
}

#: One element of each kind cryptoros cannot express, next to two that it can.
MIXED = """\
<?xml version="1.0" encoding="UTF-8"?>
<policy version="0.2.0" xmlns:xi="http://www.w3.org/2001/XInclude">
  <enclaves>
    <enclave path="/lab/arm">
      <profiles>
        <profile ns="/" node="arm">
          <xi:include href="common/node.xml" xpointer="xpointer(/profile/*)"/>
          <topics publish="ALLOW" subscribe="DENY">
            <topic>joint_states</topic>
            <topic>camera/*</topic>
            <topic>/parameter_events</topic>
            <topic>untyped</topic>
          </topics>
          <topics publish="DENY">
            <topic>forbidden</topic>
          </topics>
          <topics publish="ALLOW">
            <topic>forbidden</topic>
          </topics>
          <services reply="ALLOW" request="ALLOW">
            <service>~/get_parameters</service>
            <service>home</service>
          </services>
          <actions call="ALLOW" execute="ALLOW">
            <action>move</action>
          </actions>
        </profile>
        <profile ns="/" node="cam?ra">
          <topics publish="ALLOW">
            <topic>image</topic>
          </topics>
        </profile>
      </profiles>
    </enclave>
    <enclave path="/lab/stranger">
      <profiles>
        <profile ns="/" node="stranger">
          <topics subscribe="ALLOW">
            <topic>joint_states</topic>
          </topics>
        </profile>
      </profiles>
    </enclave>
  </enclaves>
</policy>
"""

MIXED_TYPES = {"/joint_states": "sensor_msgs/msg/JointState", "/forbidden": "std_msgs/msg/String",
               "/home": "std_srvs/srv/Trigger", "/image": "sensor_msgs/msg/Image"}


# ---------------------------------------------------------------------- the schema's rules
# Written from sros2's sros2/sros2/policy/schemas/policy.xsd (version 0.2.0), element by
# element: the tests cannot fetch the XSD, so its rules are checked here by hand.
RULE_ELEMENTS = {"topics": ("topic", {"publish", "subscribe"}), "services": ("service", {"reply", "request"}),
                 "actions": ("action", {"call", "execute"})}
XML_BASE = "{http://www.w3.org/XML/1998/namespace}base"


def _no_text(el: ET.Element) -> None:
    assert not (el.text or "").strip(), f"<{el.tag}> holds text"
    for child in el:
        assert not (child.tail or "").strip(), f"text after <{child.tag}>"


def assert_sros2_schema(text: str) -> None:
    root = ET.fromstring(text.encode())
    # <xs:element name="policy" type="Policy"/>: version required, fixed 0.2.0; one <enclaves>
    assert root.tag == "policy"
    assert set(root.attrib) == {"version"} and root.get("version") == "0.2.0"
    _no_text(root)
    assert [c.tag for c in root] == ["enclaves"]
    # Enclaves: a sequence of one or more <enclave>
    enclaves = root[0]
    assert not enclaves.attrib and len(enclaves) >= 1 and all(c.tag == "enclave" for c in enclaves)
    _no_text(enclaves)
    for enclave in enclaves:
        # Enclave: path required; one or more <profiles>
        assert set(enclave.attrib) == {"path"} and enclave.get("path")
        assert len(enclave) >= 1 and all(c.tag == "profiles" for c in enclave)
        _no_text(enclave)
        for profiles in enclave:
            # Profiles: type optional; one or more <profile>, then at most one <metadata>
            assert set(profiles.attrib) <= {"type"}
            tags = [c.tag for c in profiles]
            n = len(tags) - (1 if tags and tags[-1] == "metadata" else 0)
            assert n >= 1 and tags[:n] == ["profile"] * n, tags
            _no_text(profiles)
            for profile in profiles[:n]:
                # Profile: ns and node required, xml:base optional; any number of topics,
                # services, actions in any order
                assert {"ns", "node"} <= set(profile.attrib) <= {"ns", "node", XML_BASE}
                assert all(c.tag in RULE_ELEMENTS for c in profile)
                _no_text(profile)
                for rule in profile:
                    child, qualifiers = RULE_ELEMENTS[rule.tag]
                    # attributes optional, RuleQualifier: ALLOW or DENY
                    assert set(rule.attrib) <= qualifiers | {XML_BASE}
                    assert all(rule.get(q) in ("ALLOW", "DENY") for q in qualifiers if q in rule.attrib)
                    # one or more expressions, each a plain string
                    assert len(rule) >= 1 and all(c.tag == child for c in rule)
                    _no_text(rule)
                    for expr in rule:
                        assert not expr.attrib and len(expr) == 0 and expr.text and expr.text.strip()
                        assert not expr.text.startswith(("rt/", "rq/", "rr/")), "DDS names are not policy names"


# ---------------------------------------------------------------------- pure functions
def team_map() -> ManagerMap:
    return ManagerMap.parse(["/team/robot_a=robot_a", "/team/*=robot_b"])


def test_names_resolve_as_sros2_resolves_them():
    assert resolve("chatter", "/", "talker") == "/chatter"
    assert resolve("map", "/robot_a", "mapper") == "/robot_a/map"
    assert resolve("map", "/robot_a/", "mapper") == "/robot_a/map"
    assert resolve("/scan", "/robot_a", "mapper") == "/scan"
    assert resolve("~/reset", "/robot_a", "mapper") == "/robot_a/mapper/reset"
    assert resolve("~/reset", "/", "talker") == "/talker/reset"


def test_team_policy_gives_exactly_its_grants():
    imported = grants_from_sros2(TEAM, team_map(), TEAM_TYPES)
    assert imported.grants == TEAM_GRANTS
    assert imported.notes == []


def test_team_policy_exports_back_to_the_same_grants_and_passes_the_schema_rules():
    for manager, grants in TEAM_GRANTS.items():
        exported = sros2_from_grants(grants, enclave=f"/team/{manager}")
        assert_sros2_schema(exported.xml)
        assert exported.notes == []
        assert exported.types == {g.name: g.type for g in grants}
        again = grants_from_sros2(exported.xml, team_map(), exported.types)
        assert again.grants == {manager: grants} and again.notes == []


def test_export_writes_names_relative_to_the_profile_namespace():
    exported = sros2_from_grants(TEAM_GRANTS["robot_a"], enclave="/team/robot_a")
    root = ET.fromstring(exported.xml)
    profiles = {(p.get("ns"), p.get("node")): p for p in root.iter("profile")}
    assert set(profiles) == {("/", "talker"), ("/robot_a", "mapper")}
    mapper = profiles[("/robot_a", "mapper")]
    topics = {(tuple(sorted(r.attrib.items())), tuple(t.text for t in r)) for r in mapper.iter("topics")}
    assert topics == {((("publish", "ALLOW"), ("subscribe", "ALLOW")), ("map",)),
                      ((("subscribe", "ALLOW"),), ("/scan",))}
    assert [s.text for s in mapper.iter("service")] == ["/add_two_ints", "mapper/reset"]
    assert [t.text for t in profiles[("/", "talker")].iter("topic")] == ["chatter"]


def test_every_element_without_an_equivalent_is_reported_and_not_granted():
    imported = grants_from_sros2(MIXED, ManagerMap.parse(["/lab/arm=arm_mgr"]), MIXED_TYPES)
    assert imported.grants == {"arm_mgr": {
        GrantRow("publish", "/arm", "/joint_states", "sensor_msgs/msg/JointState"),
        GrantRow("serve", "/arm", "/home", "std_srvs/srv/Trigger"),
        GrantRow("call", "/arm", "/home", "std_srvs/srv/Trigger"),
    }}
    text = "\n".join(map(str, imported.notes))
    expected = [
        ("enclave /lab/arm profile ns=/ node=arm", "xi:include href='common/node.xml' not followed"),
        ("<topic>joint_states", "subscribe=DENY has no equivalent"),
        ("<topic>camera/*", "publish=ALLOW of the wildcard /camera/*"),
        ("<topic>camera/*", "subscribe=DENY has no equivalent"),
        ("<topic>/parameter_events", "never leaves the robot's domain"),
        ("<topic>untyped", "no type for /untyped"),
        ("<topic>forbidden", "publish=DENY has no equivalent"),
        ("<topic>forbidden", "publish /forbidden: not granted, a DENY of /forbidden"),
        ("<service>~/get_parameters", "/arm/get_parameters is ROS's own"),
        ("<action>move", "actions (call, execute) have no equivalent"),
        ("node=cam?ra", "node /cam?ra cannot be a grant's node"),
        ("enclave /lab/stranger", "matches no --manager-map entry: 1 grant(s) not given"),
    ]
    for where, what in expected:
        assert any(where in str(n) and what in str(n) for n in imported.notes), (where, what, text)
    # each note is one line
    assert all("\n" not in str(n) for n in imported.notes)


def test_a_deny_withholds_the_allows_it_matches_in_the_whole_enclave():
    policy = """<policy version="0.2.0"><enclaves><enclave path="/e"><profiles>
      <profile ns="/" node="a"><topics publish="ALLOW"><topic>cmd_vel</topic></topics></profile>
      <profile ns="/" node="b"><topics publish="DENY"><topic>cmd_*</topic></topics>
        <topics subscribe="ALLOW"><topic>cmd_vel</topic></topics></profile>
    </profiles></enclave></enclaves></policy>"""
    imported = grants_from_sros2(policy, ManagerMap.parse(["/e=m"]), {"/cmd_vel": "geometry_msgs/msg/Twist"})
    assert imported.grants == {"m": {GrantRow("subscribe", "/b", "/cmd_vel", "geometry_msgs/msg/Twist")}}
    assert any("a DENY of /cmd_*" in str(n) and "node=a" in str(n) for n in imported.notes)


def test_a_deny_of_a_private_name_in_a_node_pattern_still_withholds():
    policy = """<policy version="0.2.0"><enclaves><enclave path="/e"><profiles>
      <profile ns="/r" node="*"><services request="DENY"><service>~/reset</service></services></profile>
      <profile ns="/r" node="driver"><services request="ALLOW"><service>/r/driver/reset</service></services>
        <services reply="ALLOW"><service>~/status</service></services></profile>
      <profile ns="/r" node="*"><topics subscribe="ALLOW"><topic>~/state</topic></topics></profile>
    </profiles></enclave></enclaves></policy>"""
    types = {"/r/driver/reset": "std_srvs/srv/Empty", "/r/driver/status": "std_srvs/srv/Trigger"}
    imported = grants_from_sros2(policy, ManagerMap.parse(["/e=m"]), types)
    assert imported.grants == {"m": {GrantRow("serve", "/r/driver", "/r/driver/status", "std_srvs/srv/Trigger")}}
    text = "\n".join(map(str, imported.notes))
    assert "call /r/driver/reset: not granted, a DENY of /r/*/reset" in text
    assert "subscribe=ALLOW of a private name of a node pattern (/r/*/state)" in text


def test_what_export_cannot_hold_is_reported():
    grants = {
        GrantRow("publish", "/talker", "/chatter", "std_msgs/msg/String"),
        GrantRow("publish", "/old", "/chatter", "std_msgs/String"),
        GrantRow("read_param", "/talker", "/talker", "param"),
        GrantRow("subscribe", "/l", "/chatter", "std_msgs/msg/Header"),
    }
    exported = sros2_from_grants(grants, enclave="/x")
    assert_sros2_schema(exported.xml)
    text = "\n".join(map(str, exported.notes))
    assert "std_msgs/String is not a ROS 2 type" in text
    assert "parameter grants have no SROS2 equivalent" in text
    assert "/chatter: granted with several types" in text
    assert "/chatter" not in exported.types
    with pytest.raises(RegistryError, match="nothing to export"):
        sros2_from_grants({GrantRow("read_param", "/t", "/t", "param")}, enclave="/x")


@pytest.mark.parametrize("text, message", [
    ("<policy version='0.2.0'><enclaves>", "not well-formed XML"),
    ("<!DOCTYPE p [<!ENTITY a 'aaaa'>]><policy version='0.2.0'>&a;</policy>", "refused XML"),
    ("<permissions/>", "root element is <permissions>"),
    ("<policy version='0.1.0'><enclaves/></policy>", "only version 0.2.0"),
    ("<policy version='0.2.0'><enclaves><enclave path='/e'><profiles><profile ns='/' node='a'>"
     "<topics publish='MAYBE'><topic>x</topic></topics></profile></profiles></enclave></enclaves></policy>",
     "expected ALLOW or DENY"),
    ("<policy version='0.2.0'><enclaves><enclave path='/e'><profiles><profile node='a'/></profiles></enclave>"
     "</enclaves></policy>", "without the required attribute 'ns'"),
    ("<policy version='0.2.0'><enclaves><enclave path='/e'><profiles><profile ns='/' node='a'><topic>x</topic>"
     "</profile></profiles></enclave></enclaves></policy>", "unexpected element <topic>"),
])
def test_what_is_not_an_sros2_policy_is_one_error_line(text, message):
    with pytest.raises(RegistryError, match=message) as info:
        grants_from_sros2(text, ManagerMap.parse(["/e=m"]), {})
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------- the CLI on a registry
def cli(*args: str, db: str) -> subprocess.CompletedProcess:
    from click.testing import CliRunner

    from authz_server.cli import main

    res = CliRunner().invoke(main, ["--db", db, *args], env={"CRYPTOROS_AUTHZ_DB": None})
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return subprocess.CompletedProcess(args, res.exit_code, res.stdout, res.stderr)


def ok(r: subprocess.CompletedProcess) -> str:
    assert r.returncode == 0, (r.returncode, r.stdout, r.stderr)
    return r.stdout


@pytest.fixture
def registry(tmp_path):
    path = tmp_path / "registry.db"
    db = f"sqlite:///{path}"
    ok(cli("add-manager", "robot_a", "--fingerprint", FP_A, db=db))
    ok(cli("add-manager", "robot_b", "--fingerprint", FP_B, db=db))
    ok(cli("grant", "robot_b", "publish", "/old", "/status", "std_msgs/msg/String", db=db))
    return db, path


def write(tmp_path: Path, name: str, text: str) -> str:
    (tmp_path / name).write_text(text)
    return str(tmp_path / name)


def test_import_sros2_then_export_sros2_round_trips_through_the_registry(registry, tmp_path):
    db, _path = registry
    policy = write(tmp_path, "team.policy.xml", TEAM)
    types = write(tmp_path, "types.yaml", yaml.safe_dump(TEAM_TYPES))
    r = cli("import-sros2", policy, "--manager-map", "/team/robot_a=robot_a", "--manager-map", "/team/*=robot_b",
            "--types", types, db=db)
    assert ok(r).strip() == f"import-sros2 {policy}: 9 grant(s) added, 0 element(s) reported on stderr"
    assert r.stderr == ""
    doc = yaml.safe_load(ok(cli("export", db=db)))
    by_name = {m["name"]: m for m in doc["managers"]}
    assert by_name["robot_a"]["fingerprint_sha256"] == FP_A and by_name["robot_b"]["fingerprint_sha256"] == FP_B
    rows = {name: {GrantRow(action, g["node"], g.get("topic") or g.get("service"), g["type"])
                   for action, items in m["grants"].items() for g in items} for name, m in by_name.items()}
    assert rows["robot_a"] == TEAM_GRANTS["robot_a"]
    assert rows["robot_b"] == TEAM_GRANTS["robot_b"] | {GrantRow("publish", "/old", "/status", "std_msgs/msg/String")}
    # export each manager as SROS2 and read it into a fresh registry: the same grants
    fresh = f"sqlite:///{tmp_path / 'fresh.db'}"
    ok(cli("add-manager", "robot_a", "--fingerprint", FP_A, db=fresh))
    ok(cli("add-manager", "robot_b", "--fingerprint", FP_B, db=fresh))
    for manager in ("robot_a", "robot_b"):
        out, types_out = tmp_path / f"{manager}.xml", tmp_path / f"{manager}.types.yaml"
        r = cli("export-sros2", "--manager", manager, "--enclave", f"/team/{manager}", "-o", str(out),
                "--types-out", str(types_out), db=db)
        ok(r)
        assert r.stderr == ""
        assert_sros2_schema(out.read_text())
        ok(cli("import-sros2", str(out), "--manager-map", f"/team/{manager}={manager}", "--types", str(types_out),
               db=fresh))
    assert yaml.safe_load(ok(cli("export", db=fresh))) == doc


def test_import_sros2_reports_what_it_cannot_express_on_stderr(registry, tmp_path):
    db, _path = registry
    policy = write(tmp_path, "mixed.policy.xml", MIXED)
    args = ["import-sros2", policy, "--manager-map", "/lab/arm=robot_a"]
    for name, type_ in MIXED_TYPES.items():
        args += ["--type", f"{name}={type_}"]
    r = cli(*args, db=db)
    ok(r)
    reported = [line for line in r.stderr.splitlines() if line.startswith("cryptoros-authz: sros2: ")]
    assert len(reported) == len(r.stderr.splitlines()) == 14
    assert "3 grant(s) added, 14 element(s) reported" in r.stdout
    shown = ok(cli("show-manager", "robot_a", db=db))
    assert "/joint_states" in shown and "/home" in shown and "/forbidden" not in shown and "/untyped" not in shown


def test_dry_run_changes_nothing(registry, tmp_path):
    db, path = registry
    before = path.read_bytes()
    r = cli("import-sros2", write(tmp_path, "team.policy.xml", TEAM), "--manager-map", "/team/*=robot_b",
            "--types", write(tmp_path, "types.yaml", yaml.safe_dump(TEAM_TYPES)), "--dry-run", db=db)
    assert "would grant: robot_b /talker publish /chatter std_msgs/msg/String" in ok(r)
    assert path.read_bytes() == before


@pytest.mark.parametrize("case", ["bad_xml", "entities", "unknown_manager", "bad_map", "bad_type", "no_file"])
def test_bad_input_is_one_error_line_and_leaves_the_registry_unchanged(registry, tmp_path, case):
    db, path = registry
    team = write(tmp_path, "team.policy.xml", TEAM)
    args = {
        "bad_xml": [write(tmp_path, "bad.xml", TEAM[:-20]), "--manager-map", "/team/*=robot_a"],
        "entities": [write(tmp_path, "bomb.xml", "<!DOCTYPE p [<!ENTITY a 'x'><!ENTITY b '&a;&a;'>]>"
                                                  "<policy version='0.2.0'>&b;</policy>"),
                     "--manager-map", "/team/*=robot_a"],
        "unknown_manager": [team, "--manager-map", "/team/robot_a=robot_a", "--manager-map", "/team/*=robot_z"],
        "bad_map": [team, "--manager-map", "/team/robot_a"],
        "bad_type": [team, "--manager-map", "/team/*=robot_a", "--type", "/chatter=String"],
        "no_file": [str(tmp_path / "missing.xml"), "--manager-map", "/team/*=robot_a"],
    }[case]
    before, exported = path.read_bytes(), ok(cli("export", db=db))
    r = cli("import-sros2", *args, "--types", write(tmp_path, "types.yaml", yaml.safe_dump(TEAM_TYPES)), db=db)
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cryptoros-authz: error: "), r.stderr
    assert path.read_bytes() == before
    assert ok(cli("export", db=db)) == exported


def test_export_sros2_of_an_unknown_manager_is_one_error_line(registry):
    db, _path = registry
    r = cli("export-sros2", "--manager", "robot_z", db=db)
    assert r.returncode == 2 and r.stderr.strip() == "cryptoros-authz: error: unknown manager 'robot_z'"
