"""``cryptoros-authz`` verbs for writing policy without writing it by hand:
``policy from-graph`` (a draft from a live ROS 1 graph), ``import-sros2`` and
``export-sros2`` (SROS2 access-control policies in and out). ``authz_server.cli``
registers them; they change the registry only through :meth:`Registry.import_policy`.

What has no equivalent goes to stderr, one line each (``cryptoros-authz: warning:``
for a draft, ``cryptoros-authz: sros2:`` for SROS2); bad input is one error line and
changes nothing. Every YAML the registry reads (``import``'s policy, ``--types``) goes
through :func:`load_yaml`, which refuses a key given twice in one mapping.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import click

from authz_server.cli_context import registry as _registry
from authz_server.graph_policy import ManagerMap, draft_policy, read_graph
from authz_server.registry import PARAM_ACTIONS, GrantRow, PolicyImport
from cryptoros.files import POLICY_LIMIT, read_bounded
from cryptoros.errors import RegistryError

PROG = "cryptoros-authz"
_MAP_HELP = ("PATTERN=MANAGER (repeatable, first match wins): an fnmatch pattern on the {what} "
             "('/robot_a/*=robot_a'; '*' matches '/' too){extra}.")


def write_or_print(output: str | None, text: str) -> None:
    """``text`` to the file ``output`` (a file that cannot be written is one error line,
    never a traceback), or to stdout."""
    if output:
        try:
            Path(output).write_text(text)
        except OSError as exc:
            raise RegistryError(f"cannot write {output}: {exc.strerror}") from None
    else:
        click.echo(text, nl=False)


def _yaml(doc: object) -> str:
    import yaml

    return yaml.safe_dump(doc, sort_keys=False)


def _unique_key_loader() -> type:
    """A ``yaml.SafeLoader`` whose mappings refuse a key given twice: plain
    ``safe_load`` keeps the last value, so a second ``subscribe:`` under one manager's
    grants would silently drop the first list."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict = {}
                for key_node, _value in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *base' keys may be overridden
                        continue
                    key = self.construct_object(key_node, deep=True)
                    line = key_node.start_mark.line + 1
                    try:
                        first = seen.get(key)
                    except TypeError:  # an unhashable key: SafeLoader refuses it below
                        continue
                    if first is not None:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {key!r} at line {line} (first at line {first}); "
                            "merge the two", key_node.start_mark)
                    seen[key] = line
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


def load_yaml(text: str, what: str, path: str) -> object:
    """The document ``text`` holds: RegistryError, one line, on a syntax error or a key
    given twice in one mapping, as ``path:line:column: what is not valid YAML: problem``
    (``what`` names the file's role, ``path`` the file as the operator gave it)."""
    import yaml

    try:
        return yaml.load(text, Loader=_unique_key_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise RegistryError(_yaml_problem(exc, text, what, path)) from None


def _yaml_problem(exc: Exception, text: str, what: str, path: str) -> str:
    import yaml

    if isinstance(exc, yaml.MarkedYAMLError) and exc.problem_mark is not None:
        mark, problem, context = exc.problem_mark, exc.problem or "", exc.context
        if context == "while scanning an alias" and exc.context_mark is not None:
            # the place to fix is the '*' itself, not the character after it
            mark, context = exc.context_mark, None
            problem = "a value starting with '*' is a YAML alias: quote it ('*', '/robot_a/*')"
        elif "'\\t'" in problem:
            problem += " (YAML indents with spaces, not tabs)"
        if context and exc.context_mark is not None:
            problem += f" ({context} started at line {exc.context_mark.line + 1}, column {exc.context_mark.column + 1})"
        where = f"{path}:{mark.line + 1}:{mark.column + 1}"
    elif isinstance(exc, yaml.reader.ReaderError):
        line = text.count("\n", 0, exc.position) + 1
        column = exc.position - (text.rfind("\n", 0, exc.position) + 1) + 1
        char = chr(exc.character) if isinstance(exc.character, int) else exc.character
        where, problem = f"{path}:{line}:{column}", f"character {char!r} is not allowed in YAML"
    else:  # pragma: no cover - every error PyYAML raises on text is one of the two above
        where, problem = path, " ".join(str(exc).split())
    return f"{where}: {what} is not valid YAML: {' '.join(problem.split())}"


_VERBS = {"add": "added", "remove": "removed", "bind": "bound", "unbind": "unbound", "change": "changed",
          "enable": "enabled", "disable": "disabled"}


def import_lines(report: PolicyImport, *, dry_run: bool, grant_lines: int | None) -> list[str]:
    """One line per manager an import adds, removes or changes, then per grant it adds
    or removes (``grant_lines`` of them at most, the rest counted), in the form
    ``cryptoros-authz grant`` takes them. A dry run says what it would do."""
    def said(verb: str) -> str:
        return f"would {verb}" if dry_run else _VERBS[verb]

    lines = [f"{said('add')} manager {name}" + ("" if fp else " (no certificate)")
             for name, fp in report.managers_added]
    lines += [f"{said('remove')} manager {name}" for name in sorted(report.managers_removed)]
    for name, was, now in report.certificates:
        if now is None:
            lines.append(f"{said('unbind')} the certificate of manager {name} (was {was}): "
                         f"it gets no token until '{PROG} set-cert'")
        elif was is None:
            lines.append(f"{said('bind')} manager {name} to certificate {now}")
        else:
            lines.append(f"{said('change')} the certificate of manager {name} from {was} to {now}")
    lines += [f"{said('enable' if on else 'disable')} manager {name}" for name, on in report.enabled]
    grants = [("add", m, g) for m, g in report.grants_added] + [("remove", m, g) for m, g in report.grants_removed]
    shown = grants if grant_lines is None else grants[:grant_lines]
    for verb, manager, g in shown:
        lines.append(f"{said(verb)} grant {manager} {g.action} {g.node} {g.name}"
                     + ("" if g.action in PARAM_ACTIONS else f" {g.type}"))
    if len(shown) < len(grants):
        rest = grants[len(shown):]
        added = sum(1 for verb, _m, _g in rest if verb == "add")
        lines.append(f"... and {len(rest)} more grant change(s) not listed ({added} added, {len(rest) - added} "
                     "removed; --all lists them)")
    return lines


# ---------------------------------------------------------------------- policy from-graph
@click.group("policy")
def policy() -> None:
    """Write policy from what runs: a draft from a live ROS 1 graph."""


@policy.command("from-graph")
@click.option("--master-uri", required=True,
              help="XML-RPC URI of the plain rosmaster (before cryptoros is enforced, or the master host's "
                   "loopback one), never taken from $ROS_MASTER_URI: an interceptor's local master answers "
                   "only what its grants show.")
@click.option("--manager-map", "manager_map", multiple=True, required=True, metavar="PATTERN=MANAGER",
              help=_MAP_HELP.format(what="node name", extra=", or '@HOST=MANAGER' on the host of the node's "
                                                           "XML-RPC URI"))
@click.option("--params", "param_access", type=click.Choice(["read", "write"]), default="read", show_default=True,
              help="Grant each node read_param or write_param on its private namespace when it holds parameters.")
@click.option("--timeout", type=click.FloatRange(0.1, 120), default=5.0, show_default=True,
              help="Seconds for each master call and service probe.")
@click.option("-o", "--output", type=str, help="File for the draft (default stdout).")
def from_graph(master_uri: str, manager_map: tuple[str, ...], param_access: str, timeout: float,
               output: str | None) -> None:
    """Write a first-draft policy (the 'import' YAML) from a live ROS 1 graph: each
    node's exact topics, types, served services and private parameters, granted to the
    manager --manager-map gives it. Review it, then 'cryptoros-authz import'.

    \b
    Example:
      cryptoros-authz policy from-graph --master-uri http://127.0.0.1:11311 \\
          --manager-map '/robot_a/*=robot_a' --manager-map '@10.0.0.3=robot_b' -o draft.yaml
    """
    managers = ManagerMap.parse(manager_map)
    graph = asyncio.run(read_graph(master_uri, timeout=timeout))
    draft = draft_policy(graph, managers, param_access=f"{param_access}_param")
    for warning in draft.warnings:
        click.echo(f"{PROG}: warning: {warning}", err=True)
    count = sum(len(rows) for m in draft.doc["managers"] for rows in m["grants"].values())
    header = (f"# draft policy from the ROS 1 graph at {master_uri}: review it, then add it to the registry with\n"
              "# 'cryptoros-authz import --merge' ('--dry-run' first shows what changes). A plain 'import'\n"
              "# makes the registry equal to this draft: every manager it does not name is removed.\n")
    write_or_print(output, header + _yaml(draft.doc))
    click.echo(f"{PROG}: drafted {count} grant(s) for {len(draft.doc['managers'])} manager(s) from "
               f"{len(graph.nodes)} node(s); {draft.infrastructure} left out that ROS has without a grant "
               f"(/rosout, logger services); {len(draft.warnings)} warning(s)", err=True)


# ---------------------------------------------------------------------- SROS2
def _types(type_values: tuple[str, ...], types_file: str | None) -> dict[str, str]:
    types: dict[str, str] = {}
    if types_file:
        try:
            text = read_bounded(types_file, POLICY_LIMIT).decode("utf-8")
        except OSError as exc:
            raise RegistryError(f"cannot read types file {types_file}: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            raise RegistryError(f"types file {types_file} is not UTF-8 text (byte {exc.start}: {exc.reason})") from None
        doc = load_yaml(text, "types file", types_file)
        if not isinstance(doc, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in doc.items()):
            raise RegistryError(f"types file {types_file}: expected a mapping of name to type "
                                "(/chatter: std_msgs/msg/String)")
        types.update(doc)
    for value in type_values:
        name, sep, type_ = value.partition("=")
        if not sep or not name or not type_:
            raise RegistryError(f"--type {value!r}: expected NAME=TYPE such as /chatter=std_msgs/msg/String")
        types[name] = type_
    return types


@click.command("import-sros2")
@click.argument("file", type=str)
@click.option("--manager-map", "manager_map", multiple=True, required=True, metavar="PATTERN=MANAGER",
              help=_MAP_HELP.format(what="enclave path", extra=""))
@click.option("--type", "type_values", multiple=True, metavar="NAME=TYPE",
              help="The type of a topic or service (SROS2 holds none), e.g. /chatter=std_msgs/msg/String.")
@click.option("--types", "types_file", type=str, help="YAML mapping of name to type (as export-sros2 --types-out "
                                                      "writes it).")
@click.option("--dry-run", is_flag=True, help="Print the grants it would add; change nothing.")
@click.pass_context
def import_sros2(ctx: click.Context, file: str, manager_map: tuple[str, ...], type_values: tuple[str, ...],
                 types_file: str | None, dry_run: bool) -> None:
    """Add the grants an SROS2 access-control policy FILE gives (each enclave to the
    manager --manager-map names; every manager must exist), in one transaction. What
    cryptoros cannot express (DENY, wildcards, actions, names without a type) is
    reported on stderr, one line per element, and not granted.

    \b
    Example:
      cryptoros-authz import-sros2 policy.xml --manager-map '/team/robot_a=robot_a' \\
          --types types.yaml --type /chatter=std_msgs/msg/String
    """
    from authz_server.sros2 import grants_from_sros2

    managers = ManagerMap.parse(manager_map)
    types = _types(type_values, types_file)
    try:
        text = read_bounded(file, POLICY_LIMIT)
    except OSError as exc:
        raise RegistryError(f"cannot read SROS2 policy {file}: {exc.strerror}") from None
    imported = grants_from_sros2(text, managers, types, source=file)
    reg = _registry(ctx)
    current = {m.name: m for m in reg.list_managers()}
    unknown = [m for m in managers.managers if m not in current]
    if unknown:
        raise RegistryError(f"unknown manager {unknown[0]!r} in --manager-map (add it first: "
                            f"cryptoros-authz add-manager {unknown[0]} --cert FILE)")
    for note in imported.notes:
        click.echo(f"{PROG}: sros2: {note}", err=True)
    new: dict[str, list[GrantRow]] = {name: sorted(rows - set(current[name].grants))
                                      for name, rows in imported.grants.items()}
    if dry_run:
        for name, rows in sorted(new.items()):
            for g in rows:
                click.echo(f"would grant: {name} {g.node} {g.action} {g.name} {g.type}")
        click.echo(f"import-sros2 {file}: {sum(map(len, new.values()))} grant(s) to add (dry run), "
                   f"{len(imported.notes)} element(s) reported")
        return
    doc = {"version": 1, "managers": [
        {"name": name, "fingerprint_sha256": current[name].fingerprint, "grants": _grants_doc(rows)}
        for name, rows in sorted(new.items()) if rows]}
    stats = reg.import_policy(doc, merge=True) if doc["managers"] else {"grants_added": 0}
    click.echo(f"import-sros2 {file}: {stats['grants_added']} grant(s) added, "
               f"{len(imported.notes)} element(s) reported on stderr")


def _grants_doc(rows: list[GrantRow]) -> dict[str, list[dict]]:
    from authz_server.registry import grant_key

    out: dict[str, list[dict]] = {}
    for g in rows:
        out.setdefault(g.action, []).append({"node": g.node, grant_key(g.action): g.name, "type": g.type})
    return out


@click.command("export-sros2")
@click.option("--manager", required=True, help="The manager whose ROS 2 grants become one enclave.")
@click.option("--enclave", help="The enclave path.  [default: /MANAGER]")
@click.option("-o", "--output", type=str, help="File for the policy XML (default stdout).")
@click.option("--types-out", type=str, help="Write the grants' types (which SROS2 cannot hold) to this YAML file, "
                                            "for import-sros2 --types.")
@click.pass_context
def export_sros2(ctx: click.Context, manager: str, enclave: str | None, output: str | None,
                 types_out: str | None) -> None:
    """Write MANAGER's ROS 2 topic and service grants as an SROS2 policy (version
    0.2.0, one profile per node); what SROS2 cannot hold is reported on stderr."""
    from authz_server.sros2 import sros2_from_grants

    info = _registry(ctx).get_manager(manager)
    exported = sros2_from_grants(info.grants, enclave=enclave or f"/{manager}")
    for note in exported.notes:
        click.echo(f"{PROG}: sros2: {note}", err=True)
    if types_out:
        write_or_print(types_out, _yaml(exported.types))
    write_or_print(output, exported.xml)


COMMANDS = (policy, import_sros2, export_sros2)

__all__ = ["COMMANDS", "export_sros2", "import_lines", "import_sros2", "load_yaml", "policy"]
