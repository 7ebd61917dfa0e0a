"""SROS2 access-control policies in and out of cryptoros grants (pure: text in, text out).

The SROS2 policy format (sros2's ``sros2/policy/schemas/policy.xsd``, version 0.2.0)::

    <policy version="0.2.0"><enclaves>
      <enclave path="/team/robot_a"><profiles>
        <profile ns="/" node="talker">
          <topics publish="ALLOW" subscribe="DENY"><topic>chatter</topic></topics>
          <services reply="ALLOW" request="ALLOW"><service>add_two_ints</service></services>
          <actions call="ALLOW" execute="ALLOW"><action>fibonacci</action></actions>
        </profile>
      </profiles></enclave>
    </enclaves></policy>

Names resolve as sros2's permissions template resolves them: ``/x`` as it is, ``~x``
as ``<ns>/<node>x``, anything else as ``<ns>/x`` (never with DDS's ``rt/`` prefix).

:func:`grants_from_sros2` reads one into grants per manager (an enclave's manager is
the first ``--manager-map`` entry matching its path). SROS2 holds no data types, so types
come from the caller (``--type NAME=TYPE``, ``--types FILE``). Every element without a
cryptoros equivalent is a :class:`Note`, never dropped in silence: a DENY (grants only
allow: a DENY removes every ALLOW of the enclave it matches, and is otherwise what
having no grant means), a wildcard name (grants name topics exactly), an action (the
ROS 2 role does not carry actions: their ``/_action/`` names are hidden names a grant
cannot hold), a name without a type, ROS's own topics and parameter services (they
never leave the robot's domain), an ``xi:include`` (not followed).

:func:`sros2_from_grants` writes a manager's ROS 2 grants as one enclave, one profile
per node, and the types SROS2 cannot hold as a separate mapping.
"""

from __future__ import annotations

import fnmatch
import re
import xml.etree.ElementTree as ET  # writing only; parsing goes through defusedxml
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from authz_server.graph_policy import ManagerMap
from authz_server.registry import GrantRow
from cryptoros.errors import RegistryError
from cryptoros.names import validate_node_name
from cryptoros.policy.infrastructure import ROS2_LOCAL_TOPICS

VERSION = "0.2.0"
XINCLUDE_NAMESPACES = ("http://www.w3.org/2001/XInclude", "http://www.w3.org/2003/XInclude")
QUALIFIERS = ("ALLOW", "DENY")
#: rule element -> (child element, {attribute: cryptoros action or None (no equivalent)})
RULES = {
    "topics": ("topic", {"publish": "publish", "subscribe": "subscribe"}),
    "services": ("service", {"reply": "serve", "request": "call"}),
    "actions": ("action", {"call": None, "execute": None}),
}
#: the parameter services every rclpy node serves (rcl_interfaces): never bridged
PARAMETER_SERVICES = frozenset({"describe_parameters", "get_parameter_types", "get_parameters", "list_parameters",
                                "set_parameters", "set_parameters_atomically", "get_type_description"})
_WILDCARD = re.compile(r"[*?\[\]]")
_ROS2_TYPE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*/(msg|srv)/[A-Za-z][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class Note:
    """One element with no cryptoros equivalent, and what was done instead."""

    where: str
    what: str

    def __str__(self) -> str:
        return f"{self.where}: {self.what}"


@dataclass
class Imported:
    grants: dict[str, set[GrantRow]] = field(default_factory=dict)
    notes: list[Note] = field(default_factory=list)


# ---------------------------------------------------------------------- reading
def _parse(text: bytes | str, source: str) -> ET.Element:
    import defusedxml.ElementTree as DET
    from defusedxml import DefusedXmlException

    try:
        return DET.fromstring(text, forbid_dtd=True)
    except DefusedXmlException as exc:
        raise RegistryError(f"{source}: refused XML: {exc}") from None
    except ET.ParseError as exc:
        raise RegistryError(f"{source}: not well-formed XML: {exc}") from None


def _is_include(el: ET.Element) -> bool:
    return el.tag.startswith("{") and el.tag[1:].split("}")[0] in XINCLUDE_NAMESPACES


def _children(el: ET.Element, allowed: tuple[str, ...], where: str, out: Imported) -> list[ET.Element]:
    """``el``'s element children, each one of ``allowed`` (an xi:include is a note)."""
    kids = []
    for child in el:
        if _is_include(child):
            out.notes.append(Note(where, f"xi:include href={child.get('href')!r} not followed (cryptoros reads one "
                                         "file): expand it first (xmllint --xinclude) if it holds grants"))
        elif child.tag in allowed:
            kids.append(child)
        else:
            raise RegistryError(f"{where}: unexpected element <{child.tag}> (expected "
                                f"{' or '.join(f'<{a}>' for a in allowed)})")
    return kids


def _required(el: ET.Element, attr: str, where: str) -> str:
    value = el.get(attr)
    if value is None:
        raise RegistryError(f"{where}: <{el.tag}> without the required attribute {attr!r}")
    return value


def _namespace(ns: str) -> str:
    """A profile's ``ns`` as a prefix ending in ``/`` (sros2's DelimitNamespace)."""
    return "/" + ns.strip("/") + "/" if ns.strip("/") else "/"


def resolve(name: str, ns: str, node: str) -> str:
    """A policy name as sros2's permissions template resolves it."""
    if name.startswith("/"):
        return name
    if name.startswith("~"):
        return _namespace(ns) + node + name[1:]
    return _namespace(ns) + name


def profile_node(ns: str, node: str) -> str:
    """The cryptoros node name (or pattern) of a profile: ``*`` for any node."""
    if node == "*" and _namespace(ns) == "/":
        return "*"
    return _namespace(ns) + node


def _read_types(types: Mapping[str, str]) -> dict[str, str]:
    from cryptoros.names import validate_graph_name, validate_type

    out = {}
    for name, type_ in types.items():
        validate_graph_name(name, "name in the types")
        out[name] = validate_type(type_)
    return out


def grants_from_sros2(text: bytes | str, managers: ManagerMap, types: Mapping[str, str], *,
                      source: str = "policy") -> Imported:
    """The grants an SROS2 policy gives each manager, and a note per element with no
    equivalent. Raises :class:`RegistryError` (one line) on XML that is not an SROS2
    policy of version 0.2.0."""
    types = _read_types(types)
    out = Imported()
    root = _parse(text, source)
    if root.tag != "policy":
        raise RegistryError(f"{source}: the root element is <{root.tag}>, not <policy>")
    if root.get("version") != VERSION:
        raise RegistryError(f"{source}: <policy version={root.get('version')!r}>: only version {VERSION} is read")
    enclaves_el = _children(root, ("enclaves",), source, out)
    if len(enclaves_el) != 1:
        raise RegistryError(f"{source}: <policy> must hold exactly one <enclaves>")
    for enclave in _children(enclaves_el[0], ("enclave",), f"{source}: <enclaves>", out):
        path = _required(enclave, "path", f"{source}: <enclave>")
        where = f"enclave {path}"
        manager = managers.manager_for(path)
        profiles_els = _children(enclave, ("profiles",), where, out)
        if not profiles_els:
            raise RegistryError(f"{where}: no <profiles>")
        allowed: list[tuple[GrantRow, str]] = []  # (grant, where)
        denied: list[tuple[str, str, str]] = []  # (action, resolved expression, where)
        for profiles in profiles_els:
            kids = _children(profiles, ("profile", "metadata"), where, out)
            if not any(k.tag == "profile" for k in kids):
                raise RegistryError(f"{where}: <profiles> without a <profile>")
            for profile in kids:
                if profile.tag == "metadata":
                    out.notes.append(Note(where, "<metadata> ignored"))
                    continue
                ns, node = _required(profile, "ns", where), _required(profile, "node", where)
                pwhere = f"{where} profile ns={ns} node={node}"
                _read_profile(profile, ns, node, pwhere, types, out, allowed, denied)
        if manager is None:
            out.notes.append(Note(where, f"matches no --manager-map entry: {len(allowed)} grant(s) not given"))
            continue
        for grant, gwhere in allowed:
            blocker = next((expr for action, expr, _w in denied
                            if action == grant.action and fnmatch.fnmatchcase(grant.name, expr)), None)
            if blocker is not None:
                out.notes.append(Note(gwhere, f"{grant.action} {grant.name}: not granted, a DENY of {blocker} in "
                                              "this enclave matches it"))
                continue
            out.grants.setdefault(manager, set()).add(grant)
    return out


def _read_profile(profile: ET.Element, ns: str, node: str, where: str, types: Mapping[str, str], out: Imported,
                  allowed: list, denied: list) -> None:
    node_name = profile_node(ns, node)
    node_ok = True
    try:
        if _WILDCARD.search(node_name[:-1] if node_name.endswith("*") else node_name):
            raise RegistryError("only one trailing '*' is a node pattern")
        validate_node_name(node_name)
    except RegistryError as exc:
        out.notes.append(Note(where, f"node {node_name} cannot be a grant's node ({exc}): nothing of this profile "
                                     "is granted"))
        node_ok = False
    for rule in _children(profile, tuple(RULES), where, out):
        child_tag, qualifiers = RULES[rule.tag]
        for attr in rule.attrib:
            if attr not in qualifiers and not attr.startswith("{"):
                raise RegistryError(f"{where}: <{rule.tag}> has an unknown attribute {attr!r}")
        rule_q = {}
        for attr in qualifiers:
            value = rule.get(attr)
            if value is not None and value not in QUALIFIERS:
                raise RegistryError(f"{where}: <{rule.tag} {attr}={value!r}>: expected ALLOW or DENY")
            if value is not None:
                rule_q[attr] = value
        names = _children(rule, (child_tag,), where, out)
        if not names:
            raise RegistryError(f"{where}: <{rule.tag}> without a <{child_tag}>")
        for el in names:
            expr = (el.text or "").strip()
            if not expr:
                raise RegistryError(f"{where}: an empty <{child_tag}>")
            ewhere = f"{where} <{child_tag}>{expr}"
            if rule.tag == "actions":
                out.notes.append(Note(ewhere, f"actions ({', '.join(sorted(rule_q))}) have no equivalent: the ROS 2 "
                                              "role does not carry actions (their /_action/ topics and services "
                                              "are hidden names a grant cannot hold): not granted"))
                continue
            name = resolve(expr, ns, node)
            allows = [attr for attr, value in sorted(rule_q.items()) if value == "ALLOW"]
            for attr in sorted(a for a, value in rule_q.items() if value == "DENY"):
                denied.append((qualifiers[attr], name, ewhere))
                out.notes.append(Note(ewhere, f"{attr}=DENY has no equivalent (grants only allow; no grant is a "
                                              f"denial): it withholds every {qualifiers[attr]} ALLOW of this "
                                              "enclave it matches"))
            if not allows or not node_ok:
                continue
            said = "/".join(allows) + "=ALLOW"
            if "*" in node_name and expr.startswith("~"):
                out.notes.append(Note(ewhere, f"{said} of a private name of a node pattern ({name}) names no one "
                                              f"{child_tag}: not granted"))
                continue
            if _WILDCARD.search(name):
                out.notes.append(Note(ewhere, f"{said} of the wildcard {name}: grants name each {child_tag} "
                                              "exactly: not granted"))
                continue
            if _stays_local(rule.tag, name, node_name):
                out.notes.append(Note(ewhere, f"{name} is ROS's own and never leaves the robot's domain: needs "
                                              "no grant"))
                continue
            type_ = types.get(name)
            if type_ is None:
                out.notes.append(Note(ewhere, f"{said}: no type for {name} (SROS2 holds none; give --type "
                                              f"{name}=pkg/{'msg' if child_tag == 'topic' else 'srv'}/Name): "
                                              "not granted"))
                continue
            for attr in allows:
                try:
                    allowed.append((GrantRow.checked(qualifiers[attr], node_name, name, type_), ewhere))
                except RegistryError as exc:
                    out.notes.append(Note(ewhere, f"{attr}=ALLOW: {exc}: not granted"))


def _stays_local(kind: str, name: str, node: str) -> bool:
    if kind == "topics":
        return name in ROS2_LOCAL_TOPICS
    if node != "*" and name.startswith(node + "/"):
        return name[len(node) + 1:] in PARAMETER_SERVICES
    return False


# ---------------------------------------------------------------------- writing
@dataclass
class Exported:
    xml: str
    types: dict[str, str]
    notes: list[Note] = field(default_factory=list)


def _split_node(node: str) -> tuple[str, str]:
    """A grant's node as a profile's (ns, node)."""
    if node == "*":
        return "/", "*"
    ns, _sep, base = node.rpartition("/")
    return ns or "/", base


def _relative(name: str, ns: str) -> str:
    prefix = _namespace(ns)
    return name[len(prefix):] if name.startswith(prefix) else name


def sros2_from_grants(grants: Iterable[GrantRow], *, enclave: str) -> Exported:
    """One enclave ``enclave`` holding a profile per node of ``grants`` (their ROS 2
    topics and services); what SROS2 cannot hold is a note (parameters, ROS 1 types,
    node names it cannot carry). Raises RegistryError when nothing can be written
    (the schema needs at least one profile)."""
    notes: list[Note] = []
    types: dict[str, str] = {}
    conflicts: set[str] = set()
    per_node: dict[str, dict[str, set[str]]] = {}
    for g in sorted(grants):
        where = f"{g.action} {g.node} {g.name}"
        if g.action in ("read_param", "write_param"):
            notes.append(Note(where, "parameter grants have no SROS2 equivalent (ROS 2 parameters are node "
                                     "services): not exported"))
            continue
        if not _ROS2_TYPE.match(g.type):
            notes.append(Note(where, f"{g.type} is not a ROS 2 type (pkg/msg/Name, pkg/srv/Name): not exported"))
            continue
        if g.node != "*" and _WILDCARD.search(g.node[:-1]):
            notes.append(Note(where, "node name cannot be a profile: not exported"))
            continue
        if types.setdefault(g.name, g.type) != g.type:
            conflicts.add(g.name)
        per_node.setdefault(g.node, {}).setdefault(g.name, set()).add(g.action)
    for name in sorted(conflicts):
        notes.append(Note(name, "granted with several types: SROS2 holds none, and the types file leaves it out "
                                "(import-sros2 then needs --type for it)"))
        del types[name]
    if not per_node:
        raise RegistryError("nothing to export as SROS2: no topic or service grant with a ROS 2 type")
    root = ET.Element("policy", version=VERSION)
    profiles = ET.SubElement(ET.SubElement(ET.SubElement(root, "enclaves"), "enclave", path=enclave), "profiles")
    for node in sorted(per_node):
        ns, base = _split_node(node)
        profile = ET.SubElement(profiles, "profile", ns=ns, node=base)
        names = per_node[node]
        for tag, (child, qualifiers) in (("topics", RULES["topics"]), ("services", RULES["services"])):
            groups: dict[tuple[str, ...], list[str]] = {}
            for name, actions in names.items():
                attrs = tuple(attr for attr, action in qualifiers.items() if action in actions)
                if attrs:
                    groups.setdefault(attrs, []).append(name)
            for attrs in sorted(groups, key=lambda a: (-len(a), a)):
                rule = ET.SubElement(profile, tag, {attr: "ALLOW" for attr in attrs})
                for name in sorted(groups[attrs]):
                    ET.SubElement(rule, child).text = _relative(name, ns)
    ET.indent(root)
    text = '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
    return Exported(xml=text, types=dict(sorted(types.items())), notes=notes)


__all__ = ["Exported", "Imported", "Note", "PARAMETER_SERVICES", "VERSION", "grants_from_sros2", "profile_node",
           "resolve", "sros2_from_grants"]
