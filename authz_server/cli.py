"""``cryptoros-authz``: admin verbs over the registry, and ``serve`` for the daemon.

The verbs of policy authoring and learning live in :mod:`authz_server.policy_cli` and
:mod:`authz_server.learn_cli`; the rest are one screen each, kept together.

Every verb takes the registry URL from ``--db`` or ``CRYPTOROS_AUTHZ_DB`` (default
``sqlite:///./cryptoros-authz.db``); ``serve --config FILE`` also from the file's ``db``,
where ``--db`` wins and a ``CRYPTOROS_AUTHZ_DB`` that differs from it is refused
(:func:`serve_db`). Bad input (unknown manager, invalid ROS name or
type, malformed policy, missing file) prints one line ``cryptoros-authz: error: ...``
on stderr, exits with status 2 and changes nothing. A daemon that cannot start (port
taken, database unreachable) exits with status 1 and one line, never a traceback.

Every verb that changes the registry is recorded with who ran it (OS user, host, the
command line without ``--db``) and what it changed; ``audit --changes`` lists the
record and ``audit --verify`` checks its hash chain.
"""

from __future__ import annotations

import difflib
import json
import logging
import os
import sys
import time
from pathlib import Path

import click
from sqlalchemy.exc import SQLAlchemyError

from authz_server import keys as keymod
from authz_server.changes import parse_since, summary
from authz_server.cli_context import registry as _registry
from authz_server.db import DEFAULT_DB_URL, current_revision, head_revision, make_engine, shown_db
from authz_server.registry import ACTIONS, MAX_CERT_OVERLAP_S, PARAM_ACTIONS, GrantRow, Registry, validate_manager_name
from cryptoros.files import PEM_LIMIT, POLICY_LIMIT, read_bounded
from cryptoros.errors import ConfigError, CryptorosError, PKIError, RegistryError, TokenError
from cryptoros import logfmt
from cryptoros.lazy import LazyGroup

PROG = "cryptoros-authz"
DB_ENV = "CRYPTOROS_AUTHZ_DB"


class _Group(LazyGroup):
    """Turns our errors into one line on stderr: exit 2 for bad input, 1 otherwise. The
    verbs of policy authoring and learning are imported when named (:data:`_LAZY`)."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except click.UsageError as exc:
            hint = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
            click.echo(f"{PROG}: error: {' '.join(exc.format_message().split())}{hint}", err=True)
            ctx.exit(2)
        except (RegistryError, ConfigError, PKIError) as exc:
            click.echo(f"{PROG}: error: {exc}", err=True)
            ctx.exit(2)
        except CryptorosError as exc:
            click.echo(f"{PROG}: error: {exc}", err=True)
            ctx.exit(1)
        except SQLAlchemyError as exc:  # a write refused at commit (a full disk): rolled back whole
            cause = getattr(exc, "orig", None) or exc
            if _read_only(cause):  # the operator's to fix, as a wrong --db is: status 2
                click.echo(f"{PROG}: error: the registry database is read-only for this user "
                           f"({' '.join(str(cause).split())[:200]}); nothing was changed: run as its owner, "
                           "or make the file and its directory writable", err=True)
                ctx.exit(2)
            click.echo(f"{PROG}: error: the registry database failed ({' '.join(str(cause).split())[:200]}); "
                       "nothing was changed", err=True)
            ctx.exit(1)


def _read_only(cause: BaseException) -> bool:
    """Whether a database error is a write refused because the registry is read-only: an
    SQLite file the user may not write (SQLITE_READONLY and its extended codes), or a
    PostgreSQL read-only transaction (a standby: SQLSTATE 25006)."""
    code = getattr(cause, "sqlite_errorcode", None)
    if code is not None:
        return code & 0xFF == 8  # SQLITE_READONLY
    return getattr(cause, "sqlstate", None) == "25006"


#: verbs imported only when named: they pull in the policy and token code (jwt,
#: cryptography), about a tenth of the CPU of every other verb's call
_LAZY = {
    "policy": "authz_server.policy_cli:policy",
    "import-sros2": "authz_server.policy_cli:import_sros2",
    "export-sros2": "authz_server.policy_cli:export_sros2",
    "learn": "authz_server.learn_cli:learn",
    "unused": "authz_server.learn_cli:unused_cmd",
}


@click.group(cls=_Group, subcommands=_LAZY, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--db", "db_url", envvar=DB_ENV, default=DEFAULT_DB_URL, show_default=True,
              help=f"Registry database URL (SQLAlchemy; or ${DB_ENV}).")
@click.version_option(package_name="cryptoros")
@click.pass_context
def main(ctx: click.Context, db_url: str) -> None:
    """cryptoros-authz: the authorization registry and access-token issuer."""
    ctx.obj = {"db": db_url}


def _fingerprint_of(cert_file: str, name: str | None = None, ca_file: str | None = None) -> str:
    from cryptography.hazmat.primitives import serialization

    from cryptoros import pemfiles
    from cryptoros.identity import identity_mismatch, named_holders

    try:
        cert = pemfiles.load_certificate(cert_file)
    except PKIError as exc:
        raise RegistryError(str(exc)) from exc
    now = time.time()
    if cert.not_valid_after_utc.timestamp() <= now:  # no token could ever be issued to it: a wrong file
        raise RegistryError(f"{cert_file} expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC: renew it "
                            f"(cryptoros-certs renew) and give the new one")
    if cert.not_valid_before_utc.timestamp() > now:
        raise RegistryError(f"{cert_file} is not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC "
                            f"(a clock off on the CA's machine?)")
    if name is not None:
        mismatch = identity_mismatch(named_holders(cert), name)
        if mismatch is not None:
            raise RegistryError(f"{cert_file} {mismatch}")
    _check_client_certificate(cert, cert_file, ca_file)
    return pemfiles.cert_fingerprint_sha256(cert.public_bytes(serialization.Encoding.DER))


def _check_client_certificate(cert, cert_file: str, ca_file: str | None) -> None:
    """A certificate a manager's client may present: not a CA's, not a server's, issued
    by the fleet's CA and not revoked by its CRL. The CA is ``ca_file``, else the
    ``ca.crt`` of ``$CRYPTOROS_PKI_DIR``, else of the cryptoros-certs directory the
    certificate lies in (``pki/issued/NAME.crt``), with its ``crl.pem``; without any the
    issuer is not checked. (CLI audit: another CA's certificate was bound with exit 0,
    and the robot locked out: every TLS handshake with its real one failed.)"""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    from cryptoros import pemfiles

    try:
        if cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca:
            raise RegistryError(f"{cert_file} is a CA certificate, not a manager's client certificate")
    except x509.ExtensionNotFound:
        pass
    kinds = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)]
    if "server" in kinds:
        raise RegistryError(f"{cert_file} is a server certificate (kind server), not a manager's client certificate")
    named = os.environ.get(PKI_DIR_ENV)
    if ca_file is None and named:
        if not (Path(named) / "ca.crt").is_file():
            raise RegistryError(f"{PKI_DIR_ENV}={named} holds no ca.crt: the fleet's CA to check {cert_file} "
                                "against (give --ca FILE, or fix the variable)")
        ca_file = str(Path(named) / "ca.crt")
    if ca_file is None and (Path(cert_file).resolve().parent.parent / "ca.crt").is_file():
        ca_file = str(Path(cert_file).resolve().parent.parent / "ca.crt")
    if ca_file is None:
        click.echo(f"warning: the issuer of {cert_file} was not checked: no fleet CA found (give --ca FILE, or set "
                   f"{PKI_DIR_ENV} to the cryptoros-certs directory)", err=True)
        return
    try:
        cas = pemfiles.load_certificates(ca_file)
    except PKIError as exc:
        raise RegistryError(f"cannot read the fleet's CA: {exc}") from None
    if not pemfiles.issued_by_any(cert, cas):  # a file of several CAs (a CA being replaced): any of them
        raise RegistryError(f"{cert_file} was not issued by the fleet's CA {ca_file} (issuer: "
                            f"{cert.issuer.rfc4514_string()}): its client could not connect")
    crl_file = Path(ca_file).resolve().parent / "crl.pem"
    if not crl_file.is_file():
        click.echo(f"warning: {cert_file} was not checked against a CRL: no crl.pem beside {ca_file}", err=True)
    else:
        try:
            crl = pemfiles.load_crl(crl_file)
        except PKIError:
            return  # the CRL is the servers' to refuse; binding is not decided by it
        if crl.get_revoked_certificate_by_serial_number(cert.serial_number) is not None:
            raise RegistryError(f"{cert_file} (serial {cert.serial_number:x}) is revoked by {crl_file}")


PKI_DIR_ENV = "CRYPTOROS_PKI_DIR"
CA_HELP = ("The fleet's CA certificate: --cert must be issued by it and not revoked by the crl.pem beside it "
           f"(default: the ca.crt of ${PKI_DIR_ENV}, else of the cryptoros-certs directory --cert lies in).")


def _cert_or_fp(name: str, cert: str | None, fingerprint: str | None, ca: str | None = None) -> str | None:
    if cert and fingerprint:
        raise RegistryError("give either --cert or --fingerprint, not both")
    if cert:
        return _fingerprint_of(cert, name, ca)
    return fingerprint


# ---------------------------------------------------------------------- db
@main.group()
def db() -> None:
    """Schema migrations of the registry database."""


@db.command("upgrade")
@click.pass_context
def db_upgrade(ctx: click.Context) -> None:
    """Create the registry or migrate it to the newest schema."""
    reg = _registry(ctx.find_root(), create=True)
    click.echo(f"registry at schema revision {current_revision(reg.engine)} (head {head_revision()})")


@db.command("current")
@click.pass_context
def db_current(ctx: click.Context) -> None:
    """Print the schema revision of the registry database (no migration)."""
    engine = make_engine(ctx.find_root().obj["db"])
    try:
        click.echo(f"{current_revision(engine) or 'empty'} (head {head_revision()})")
    finally:
        engine.dispose()


# ---------------------------------------------------------------------- managers
@main.command("add-manager")
@click.argument("name")
@click.option("--cert", "cert", type=str, help="The manager's client certificate (PEM or DER).")
@click.option("--fingerprint", help="SHA-256 fingerprint of the certificate instead of --cert.")
@click.option("--disabled", is_flag=True, help="Create it disabled.")
@click.option("--ca", "ca", type=str, help=CA_HELP)
@click.pass_context
def add_manager(ctx: click.Context, name: str, cert: str | None, fingerprint: str | None, disabled: bool,
                ca: str | None) -> None:
    """Add manager NAME bound to its client certificate."""
    validate_manager_name(name)
    fp = _cert_or_fp(name, cert, fingerprint, ca)
    if fp is None:
        raise RegistryError("add-manager needs --cert FILE (or --fingerprint HEX)")
    info = _registry(ctx, create=True).add_manager(name, fp, enabled=not disabled)
    click.echo(f"added manager {info.name} (certificate sha256 {info.fingerprint}){' disabled' if disabled else ''}")


@main.command("set-cert")
@click.argument("name")
@click.option("--cert", "cert", type=str, help="The manager's new certificate.")
@click.option("--fingerprint", help="SHA-256 fingerprint instead of --cert.")
@click.option("--overlap", type=click.FloatRange(0, MAX_CERT_OVERLAP_S), default=0.0, show_default=True,
              help="A planned renewal: seconds the old certificate is still accepted, no token revoked, so the "
                   "robot keeps its streams until its interceptor reloads (SIGHUP) with the new one. 0: the old "
                   "one is refused at once and the manager's outstanding tokens revoked (a key that may be "
                   "compromised).")
@click.option("--ca", "ca", type=str, help=CA_HELP)
@click.pass_context
def set_cert(ctx: click.Context, name: str, cert: str | None, fingerprint: str | None, overlap: float,
             ca: str | None) -> None:
    """Bind manager NAME to a renewed certificate (by default the old one's tokens are revoked)."""
    validate_manager_name(name)
    fp = _cert_or_fp(name, cert, fingerprint, ca)
    if fp is None:
        raise RegistryError("set-cert needs --cert FILE (or --fingerprint HEX)")
    revoked = _registry(ctx).set_cert(name, fp, overlap=overlap)
    if overlap:
        click.echo(f"manager {name} now bound to certificate sha256 {fp.replace(':', '').lower()}; its previous "
                   f"certificate is accepted for {overlap:g} s more (revoke its serial to end that everywhere)")
    else:
        click.echo(f"manager {name} now bound to certificate sha256 {fp.replace(':', '').lower()}; "
                   f"{revoked} outstanding token(s) revoked")


@main.command("list-managers")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.pass_context
def list_managers(ctx: click.Context, as_json: bool) -> None:
    """List managers, their certificates and how many grants they hold."""
    ms = _registry(ctx).list_managers()
    if as_json:
        click.echo(json.dumps([{"name": m.name, "fingerprint_sha256": m.fingerprint, "enabled": m.enabled,
                                "grants": len(m.grants), "previous_fingerprint_sha256": m.previous_fingerprint,
                                "previous_until": m.previous_until} for m in ms], indent=2))
        return
    click.echo(f"{'NAME':20} {'ENABLED':8} {'GRANTS':>6}  CERTIFICATE SHA-256")
    for m in ms:
        click.echo(f"{m.name:20} {'yes' if m.enabled else 'no':8} {len(m.grants):>6}  {m.fingerprint or '-'}")


@main.command("show-manager")
@click.argument("name")
@click.pass_context
def show_manager(ctx: click.Context, name: str) -> None:
    """Show one manager and all of its grants."""
    m = _registry(ctx).get_manager(name)
    click.echo(f"manager {m.name}: {'enabled' if m.enabled else 'DISABLED'}, certificate sha256 {m.fingerprint or '-'}")
    if m.previous_fingerprint:
        left = (m.previous_until or 0) - time.time()
        click.echo(f"  previous certificate sha256 {m.previous_fingerprint} accepted for {left:.0f} s more")
    for g in m.grants:
        click.echo(f"  {g.action:9} {g.node:24} {g.name:32} {g.type}")


def _set_enabled(ctx: click.Context, name: str, enabled: bool) -> None:
    changed = _registry(ctx).set_enabled(name, enabled)
    state = "enabled" if enabled else "disabled"
    click.echo(f"manager {name} {state}" if changed else f"manager {name} was already {state}")


@main.command("disable-manager")
@click.argument("name")
@click.pass_context
def disable_manager(ctx: click.Context, name: str) -> None:
    """Disable NAME: no new tokens, and its live tokens appear in the revocation feed."""
    _set_enabled(ctx, name, False)


@main.command("enable-manager")
@click.argument("name")
@click.pass_context
def enable_manager(ctx: click.Context, name: str) -> None:
    """Enable NAME again."""
    _set_enabled(ctx, name, True)


@main.command("remove-manager")
@click.argument("name")
@click.pass_context
def remove_manager(ctx: click.Context, name: str) -> None:
    """Delete NAME and its grants; its live tokens are revoked."""
    _registry(ctx).remove_manager(name)
    click.echo(f"removed manager {name}")


# ---------------------------------------------------------------------- grants
@main.command("grant")
@click.argument("manager")
@click.argument("action", type=click.Choice(ACTIONS))
@click.argument("node")
@click.argument("name")
@click.argument("type_", metavar="[TYPE]", required=False)
@click.pass_context
def grant(ctx: click.Context, manager: str, action: str, node: str, name: str, type_: str | None) -> None:
    """Let MANAGER's NODE ACTION (publish|subscribe|serve|call) topic or service NAME of
    TYPE, or read_param|write_param the parameter namespace NAME (no TYPE; write
    implies read; NAME / is every parameter).

    \b
    Examples:
      cryptoros-authz grant alice publish /talker /chatter std_msgs/String
      cryptoros-authz grant alice read_param '*' /robot1
      cryptoros-authz grant alice write_param /planner /robot1/goals
    """
    reg = _registry(ctx)
    added = reg.grant(manager, action, node, name, type_)
    click.echo(f"{'granted' if added else 'already granted'}: {manager} {node} {action} {name}{' ' + type_ if type_ else ''}")
    if added:
        from authz_server.lint import kind_of, node_overlaps, type_conflicts

        managers = reg.list_managers()
        lines = node_overlaps(manager, node, managers, type_)
        if action not in PARAM_ACTIONS:
            lines += type_conflicts(kind_of(action), name, {(m.name, g) for m in managers for g in m.grants})
        for line in lines:
            click.echo(f"warning: {line}", err=True)


@main.command("revoke")
@click.argument("manager")
@click.argument("action", type=click.Choice(ACTIONS))
@click.argument("node")
@click.argument("name")
@click.argument("type_", metavar="[TYPE]", required=False)
@click.pass_context
def revoke(ctx: click.Context, manager: str, action: str, node: str, name: str, type_: str | None) -> None:
    """Take a grant away (every type when TYPE is omitted); live tokens of MANAGER are revoked."""
    n = _registry(ctx).revoke(manager, action, node, name, type_)
    click.echo(f"revoked {n} grant(s): {manager} {node} {action} {name}{' ' + type_ if type_ else ''}")


#: What roslaunch writes besides its launch file's parameters (measured: docs/stock-tools.md).
ROSLAUNCH_PARAMS = ("/run_id", "/roslaunch", "/rosdistro", "/rosversion")


def _name_type(value: str, option: str) -> tuple[str, str]:
    name, sep, type_ = value.partition(":")
    if not sep or not name or not type_:
        raise RegistryError(f"{option} {value!r}: expected NAME:TYPE such as /chatter:std_msgs/String")
    return name, type_


def tool_grants(topics: tuple[str, ...], publish_topics: tuple[str, ...], services: tuple[str, ...],
                param_namespaces: tuple[str, ...], params_read_only: bool) -> list[tuple[str, str, str, str | None]]:
    """The (action, node, name, type) rows ``grant-tools`` grants."""
    from cryptoros.policy.hints import TOOL_NODES

    rows: list[tuple[str, str, str, str | None]] = []
    for value in topics:
        rows.append(("subscribe", TOOL_NODES["rostopic"], *_name_type(value, "--topic")))
        rows.append(("subscribe", TOOL_NODES["rosbag"], *_name_type(value, "--topic")))
    for value in publish_topics:
        rows.append(("publish", TOOL_NODES["rostopic"], *_name_type(value, "--publish-topic")))
        rows.append(("publish", TOOL_NODES["rosbag_play"], *_name_type(value, "--publish-topic")))
    for value in services:
        name, type_ = _name_type(value, "--service")
        rows.append(("call", TOOL_NODES["rosservice_probe"], name, type_))
        rows.append(("call", TOOL_NODES["rosservice"], name, type_))
    for ns in param_namespaces:
        rows.append(("read_param" if params_read_only else "write_param", TOOL_NODES["rosparam"], ns, None))
    return rows


@main.command("grant-tools")
@click.argument("manager")
@click.option("--topic", "topics", multiple=True, metavar="NAME:TYPE",
              help="A topic rostopic echo/hz/bw and rosbag record may subscribe to (repeatable).")
@click.option("--publish-topic", "publish_topics", multiple=True, metavar="NAME:TYPE",
              help="A topic rostopic pub and rosbag play may publish (repeatable).")
@click.option("--service", "services", multiple=True, metavar="NAME:TYPE",
              help="A service rosservice call may call (repeatable).")
@click.option("--param-ns", "param_namespaces", multiple=True, metavar="NS",
              help="Parameter namespace rosparam get/set/list/delete may use (repeatable; without it rosparam "
                   "is granted nothing).")
@click.option("--params-read-only", is_flag=True, help="rosparam may only read (get, list, dump) the --param-ns "
              "namespaces.")
@click.option("--clock", is_flag=True, help="rosbag play --clock may publish /clock.")
@click.option("--roslaunch", is_flag=True, help="roslaunch may write /run_id, /roslaunch, /rosdistro, /rosversion "
              "(the launched nodes' own <param>s need nothing more).")
@click.option("--launch-param-ns", "launch_namespaces", multiple=True, metavar="NS",
              help="A namespace outside the launched nodes' own where roslaunch may set <param>/<rosparam> "
                   "(repeatable; implies --roslaunch).")
@click.option("--remove", is_flag=True, help="Take the same grants away instead.")
@click.pass_context
def grant_tools(ctx: click.Context, manager: str, topics: tuple[str, ...], publish_topics: tuple[str, ...],
                services: tuple[str, ...], param_namespaces: tuple[str, ...], params_read_only: bool,
                clock: bool, roslaunch: bool, launch_namespaces: tuple[str, ...],
                remove: bool) -> None:
    """Grant MANAGER's stock ROS 1 tools what they need, by the anonymous node names
    they run under: rostopic as /rostopic_* and rosbag record as /record_* (--topic;
    --publish-topic for rostopic pub and rosbag play as /play_*, --clock for its /clock),
    rosparam as /rosparam-* (in the namespaces --param-ns names; nothing without it),
    rosservice call as /rosservice and /rosservice_* (--service), roslaunch as
    /roslaunch (--roslaunch, --launch-param-ns).
    rosnode list/info/ping and rostopic list/info/type only read the graph and need no
    grant; rosnode kill is always refused (docs/stock-tools.md). Idempotent: a grant
    already there is left as it is. All of it is one transaction.

    \b
    Example:
      cryptoros-authz grant-tools robot_b --topic /chatter:std_msgs/String \\
          --service /add_two_ints:rospy_tutorials/AddTwoInts --param-ns /robot_b
    """
    from cryptoros.policy.hints import TOOL_NODES

    if params_read_only and not param_namespaces:
        raise RegistryError("--params-read-only needs the namespaces rosparam may read: give --param-ns NS")
    rows = tool_grants(topics, publish_topics, services, param_namespaces, params_read_only)
    if clock:  # rosbag play --clock
        rows.append(("publish", TOOL_NODES["rosbag_play"], "/clock", "rosgraph_msgs/Clock"))
    if roslaunch or launch_namespaces:  # its own keys, and what its launch files set outside the nodes' own
        rows += [("write_param", TOOL_NODES["roslaunch"], ns, None) for ns in (*ROSLAUNCH_PARAMS, *launch_namespaces)]
    if not rows:
        raise RegistryError("nothing to grant: name what the tools may use (--topic, --publish-topic, --service, "
                            "--param-ns, --clock, --roslaunch)")
    checked = [GrantRow.checked(*row) for row in rows]  # all validated before the one transaction
    registry = _registry(ctx)
    done = registry.grant_many(manager, checked, remove=remove)
    if not remove:
        if "/" in param_namespaces:
            click.echo(f"{PROG}: warning: --param-ns / lets {manager}'s rosparam "
                       f"{'read' if params_read_only else 'write and delete'} every parameter, other robots' "
                       "nodes' too; name the namespace the operator needs", err=True)
        if params_read_only:  # read granted; a write grant given before stays, and writes
            held = {(g.node, g.name) for g in registry.get_manager(manager).grants if g.action == "write_param"}
            for ns in param_namespaces:
                if (TOOL_NODES["rosparam"], ns) in held:
                    click.echo(f"{PROG}: warning: {manager}'s rosparam may still write {ns} (granted before): "
                               f"'{PROG} grant-tools {manager} --param-ns {ns} --remove' takes that away", err=True)
    for (action, node, name, type_), changed_one in zip(rows, done, strict=True):
        what = f"{manager} {node} {action} {name}{' ' + type_ if type_ else ''}"
        if remove:
            click.echo(f"{'removed' if changed_one else 'not granted'}: {what}")
        else:
            click.echo(f"{'granted' if changed_one else 'already granted'}: {what}")
    changed = sum(done)
    click.echo(f"grant-tools {manager}: {changed} grant(s) {'removed' if remove else 'added'}, "
               f"{len(rows) - changed} unchanged; rosnode list/info/ping need no grant")


@main.command("export")
@click.option("-o", "--output", type=click.Path(dir_okay=False, writable=True), help="File (default stdout).")
@click.pass_context
def export(ctx: click.Context, output: str | None) -> None:
    """Write the whole policy (managers, certificates, grants) as YAML."""
    import yaml

    from authz_server.policy_cli import write_or_print

    write_or_print(output, yaml.safe_dump(_registry(ctx).export_policy(), sort_keys=False))


#: Grant lines an import lists before it only counts the rest (--all lists every one).
IMPORT_GRANT_LINES = 200


@main.command("import")
@click.argument("file", type=str)
@click.option("--merge", is_flag=True, help="Only add managers and grants; remove nothing.")
@click.option("--dry-run", is_flag=True, help="Say what the import would change, and change nothing.")
@click.option("--all", "list_all", is_flag=True,
              help=f"List every grant added or removed (by default the first {IMPORT_GRANT_LINES}).")
@click.pass_context
def import_(ctx: click.Context, file: str, merge: bool, dry_run: bool, list_all: bool) -> None:
    """Make the registry's policy equal to a YAML FILE ('-' for stdin), in one transaction.
    A key given twice in one mapping (two ``subscribe:`` lists) is an error, not the last one kept.
    A manager without a ``fingerprint_sha256`` key keeps its certificate; ``null`` unbinds it
    (not with --merge). Prints one line per manager and grant it changes, then the counts."""
    try:
        text = sys.stdin.read(POLICY_LIMIT + 1) if file == "-" else read_bounded(file, POLICY_LIMIT).decode("utf-8")
        if len(text) > POLICY_LIMIT:  # never a policy cut short: the rest would read as removed
            raise RegistryError(f"the policy on stdin is larger than {POLICY_LIMIT >> 20} MiB")
    except OSError as exc:
        raise RegistryError(f"cannot read policy file {file}: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        raise RegistryError(f"policy file {file} is not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    from authz_server.policy_cli import import_lines, load_yaml

    doc = load_yaml(text, "policy file", "<stdin>" if file == "-" else file)
    registry = _registry(ctx, create=True)
    before = registry.list_managers()
    known = [m.name for m in before]
    report = registry.import_policy_report(doc, merge=merge, dry_run=dry_run)
    for line in import_lines(report, dry_run=dry_run, grant_lines=None if list_all else IMPORT_GRANT_LINES):
        click.echo(line)
    from authz_server.lint import kind_of, type_conflicts

    held = {(m.name, g) for m in before for g in m.grants} - set(report.grants_removed) | set(report.grants_added)
    touched = sorted({(kind_of(g.action), g.name) for _m, g in report.grants_added if g.action not in PARAM_ACTIONS})
    for kind, name in touched:
        for line in type_conflicts(kind, name, held):
            click.echo(f"{PROG}: warning: {line}", err=True)
    for name, fp in report.managers_added:
        if fp is None:
            # a typo, or a rename that loses the binding: the nearest name, removed or not
            near = difflib.get_close_matches(name, known, n=1)
            removed = f", which this {'dry run would remove' if dry_run else 'import removes'} with its certificate" \
                if near and near[0] in report.managers_removed else ""
            click.echo(f"{PROG}: warning: manager {name} has no certificate: its grants reach nobody until "
                       f"'{PROG} set-cert {name} --cert FILE'" + (f" (did you mean {near[0]}{removed}?)" if near else ""),
                       err=True)
    removed = sorted(report.managers_removed)
    click.echo(("would import (dry run, nothing changed): " if dry_run else "imported: ")
               + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in report.stats.items())
               + (f"; managers removed: {', '.join(removed)}" if removed else ""))


# ---------------------------------------------------------------------- keys and tokens
class _AliasedOption(click.Option):
    """An option with old spellings that still work but are left out of --help."""

    def __init__(self, *args, hidden_aliases: tuple[str, ...] = (), **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.hidden_aliases = set(hidden_aliases)

    def get_help_record(self, ctx: click.Context):
        shown = self.opts
        self.opts = [o for o in shown if o not in self.hidden_aliases]
        try:
            return super().get_help_record(ctx)
        finally:
            self.opts = shown


_passphrase_options = [
    click.option("--signing-key-passphrase-file", "--key-passphrase-file", "signing_key_passphrase_file",
                 cls=_AliasedOption, hidden_aliases=("--key-passphrase-file",), type=str,
                 help="File holding the passphrase that encrypts the token-signing keys in the registry "
                      f"(or ${keymod.PASSPHRASE_ENV}).", ),
    click.option("--unsafe-no-passphrase", is_flag=True, help="Store signing keys unencrypted."),
]


def _with_passphrase(fn):
    for opt in reversed(_passphrase_options):
        fn = opt(fn)
    return fn


@main.command("rotate-key")
@_with_passphrase
@click.option("--bits", type=click.Choice(["2048", "3072"]), default="2048", show_default=True)
@click.option("--change-passphrase", is_flag=True,
              help="Encrypt the new key with a passphrase that does not open the current one (restart serve with it).")
@click.pass_context
def rotate_key(ctx: click.Context, signing_key_passphrase_file: str | None, unsafe_no_passphrase: bool, bits: str,
               change_passphrase: bool) -> None:
    """Create a new RS256 signing key; the old one stays in the JWKS until its tokens expire.

    The passphrase must open the current key (the one serve uses), unless --change-passphrase."""
    prot = keymod.protection(signing_key_passphrase_file, unsafe_no_passphrase=unsafe_no_passphrase)
    kid = _registry(ctx, create=True).rotate_key(prot, int(bits), change_passphrase=change_passphrase)
    click.echo(f"new signing key {kid}")


@main.command("list-keys")
@click.pass_context
def list_keys(ctx: click.Context) -> None:
    """List signing keys: active, retired."""
    for k in _registry(ctx).list_keys():
        state = "active" if k.active else f"retired {k.retired_at:%Y-%m-%d %H:%M:%S}" if k.retired_at else "inactive"
        click.echo(f"{k.kid}  created {k.created_at:%Y-%m-%d %H:%M:%S}  {state}")


@main.command("revoke-token")
@click.argument("jti")
@click.option("--reason", default="revoked by operator", show_default=True)
@click.option("--expires-at", type=click.IntRange(0, 2**31 - 1),
              help="Expiry (unix time) of a token missing from the audit log.")
@click.pass_context
def revoke_token(ctx: click.Context, jti: str, reason: str, expires_at: int | None) -> None:
    """Revoke one access token by its jti; interceptors see it on their next feed poll."""
    added = _registry(ctx).revoke_token(jti, reason=reason, expires_at=expires_at)
    click.echo(f"token {jti} {'revoked' if added else 'was already revoked'}")


@main.command("audit")
@click.option("--limit", type=click.IntRange(1, 100000),
              help="The newest rows only, this many.  [default: 50 token rows; every change]")
@click.option("--manager", help="Only token rows of this manager.")
@click.option("--event", type=click.Choice(["issued", "denied"]))
@click.option("--since", metavar="AGE|TIME", help="Only rows since then: an age (7d, 12h, 30m) or an ISO time "
                                                  "(UTC unless it says otherwise).")
@click.option("--changes", is_flag=True, help="The record of registry changes (who changed what) instead of tokens.")
@click.option("--verify", is_flag=True, help="Check the hash chain of the change record: exit 0 if intact, "
                                             "1 naming the first bad row.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object per line.")
@click.pass_context
def audit(ctx: click.Context, limit: int | None, manager: str | None, event: str | None, since: str | None,
          changes: bool, verify: bool, as_json: bool) -> None:
    """Show the audit log of issued and refused tokens, oldest first; with --changes the
    record of every registry change (time UTC, OS user and host, command, what changed);
    with --verify check that record's hash chain."""
    try:
        since_at = parse_since(since) if since is not None else None
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--since") from None
    if verify:
        if changes or since or limit or manager or event or as_json:
            raise click.UsageError("--verify takes no other option")
        _verify_changes(_registry(ctx))
        return
    if changes:
        if manager or event:
            raise click.UsageError("--manager and --event select token rows, not --changes")
        _show_changes(_registry(ctx), since_at, limit, as_json)
        return
    for e in _registry(ctx).audit(limit=limit or 50, manager=manager, event=event, since=since_at):
        if as_json:
            click.echo(json.dumps({"at": e.at.isoformat(), "event": e.event, "manager": e.manager,
                                   "fingerprint_sha256": e.cert_fingerprint, "remote": e.remote,
                                   "reason": e.reason, "jti": e.jti, "kid": e.kid, "expires_at": e.expires_at}))
        else:
            detail = f"jti={e.jti} kid={e.kid}" if e.event == "issued" else f"reason={e.reason}"
            click.echo(f"{e.at:%Y-%m-%d %H:%M:%S} {e.event:6} manager={e.manager or '-'} "
                       f"remote={e.remote or '-'} cert={(e.cert_fingerprint or '-')[:16]} {detail}")


def _verify_changes(reg: Registry) -> None:
    report = reg.verify_changes()
    if report.problem is not None:
        click.echo(f"{PROG}: change record broken: {report.problem}; the {report.rows} row(s) before it are intact",
                   err=True)
        sys.exit(1)
    click.echo(f"{report.rows} rows, chain intact (head sha256 {report.head})")


def _show_changes(reg: Registry, since, limit: int | None, as_json: bool) -> None:
    rows = reg.changes(since=since, limit=limit)
    if as_json:
        for c in rows:
            click.echo(json.dumps({"seq": c.seq, "at": c.at.isoformat(), "os_user": c.os_user, "host": c.host,
                                   "command": c.command, "target": c.target, "before": c.before,
                                   "after": c.after, "hash": c.hash}))
        return
    click.echo(f"{'#':>5}  {'TIME (UTC)':19}  {'WHO':24}  {'TARGET':24}  CHANGE  [COMMAND]")
    for c in rows:
        who = f"{c.os_user}@{c.host}"
        click.echo(f"{c.seq:>5}  {c.at:%Y-%m-%d %H:%M:%S}  {who:24}  {c.target:24}  {summary(c.before, c.after)}  "
                   f"[{c.command}]")


@main.command("verify-token")
@click.option("--jwks", "jwks_file", required=True, help="JWKS JSON file (as served at /.well-known/jwks.json).")
@click.option("--cert", "cert_file", required=True, help="Certificate the token must be bound to.")
@click.option("--token-file", required=True, help="File holding the token, or the token endpoint's JSON answer.")
@click.option("--issuer", default="cryptoros-authz", show_default=True)
@click.option("--audience", default="cryptoros", show_default=True)
@click.option("--revocations", "feed_file", help="Revocation feed JSON (GET /revocations) to check too.")
def verify_token(jwks_file: str, cert_file: str, token_file: str, issuer: str, audience: str,
                 feed_file: str | None) -> None:
    """Verify an access token offline, as an interceptor does; print its claims."""
    from cryptography.hazmat.primitives import serialization

    from cryptoros import pemfiles
    from cryptoros.tokens import KeySet, Revocations, verify_access_token

    try:
        jwks = json.loads(read_bounded(jwks_file, POLICY_LIMIT))
        raw = read_bounded(token_file, PEM_LIMIT).decode("utf-8").strip()
        feed = json.loads(read_bounded(feed_file, POLICY_LIMIT)) if feed_file else None
        cert_data = read_bounded(cert_file, PEM_LIMIT)
    except (OSError, ValueError) as exc:
        raise RegistryError(f"cannot read input: {exc}") from exc
    if raw.startswith("{"):
        try:
            raw = json.loads(raw)["access_token"]
        except (ValueError, KeyError, TypeError) as exc:
            raise RegistryError(f"{token_file} is JSON without an access_token") from exc
    try:
        cert = pemfiles.parse_certificate(cert_data, cert_file)
    except PKIError as exc:
        raise RegistryError(str(exc)) from exc
    revocations = None
    if feed is not None:
        revocations = Revocations(revoked_jtis=frozenset(feed.get("revoked_jtis", [])),
                                  disabled_subjects=frozenset(feed.get("disabled_managers", [])))
    try:
        tok = verify_access_token(raw, keys=KeySet.from_jwks(jwks), issuer=issuer, audience=audience,
                                  peer_cert_der=cert.public_bytes(serialization.Encoding.DER),
                                  revocations=revocations)
    except TokenError as exc:
        click.echo(f"{PROG}: token refused: {exc}", err=True)
        sys.exit(1)
    click.echo(json.dumps(dict(tok.claims), indent=2, sort_keys=True))
    click.echo(f"token valid: subject {tok.subject}, jti {tok.jti}, expires in "
               f"{tok.expires_at - int(time.time())} s, {len(tok.grants)} grant(s)")


# ---------------------------------------------------------------------- daemon
def _same_db(a: str, b: str) -> bool:
    """Whether two URLs name one database (an SQLite file by its real path: the runbook's
    ``$PWD/registry.db`` and a relative ``registry.db`` are one file)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        ua, ub = make_url(a), make_url(b)
    except ArgumentError:
        return a == b
    if ua.get_backend_name() == ub.get_backend_name() == "sqlite" and ua.database and ub.database:
        ua = ua.set(database=os.path.realpath(ua.database))
        ub = ub.set(database=os.path.realpath(ub.database))
    return ua == ub


def serve_db(*, flag: str | None, env: str | None, file: str | None, config_file: str | None) -> tuple[str, str]:
    """The registry ``serve`` opens and where it was named: ``--db`` wins; otherwise the
    configuration file's ``db`` and ``CRYPTOROS_AUTHZ_DB`` must agree when both are set
    (an environment variable is no flag: which one was meant is not guessed, ConfigError
    naming both); otherwise whichever is set, else the default."""
    if flag:
        return flag, "--db"
    if file and env and not _same_db(file, env):
        raise ConfigError(f"two registry databases: db = {shown_db(file)} in {config_file} and {DB_ENV}="
                          f"{shown_db(env)}; unset {DB_ENV} or remove db from the file (or pass --db)")
    if file:
        return file, f"db in {config_file}"
    if env:
        return env, DB_ENV
    return DEFAULT_DB_URL, "the default"


@main.command("serve")
@click.option("--config", "config_file", help="TOML file with any of the settings below (unknown keys are errors).")
@click.option("--host", help="Listen address.  [default: 127.0.0.1]")
@click.option("--port", type=int, help="Listen port.  [default: 8443]")
@click.option("--ca", help="CA certificate clients must chain to.")
@click.option("--cert", help="The server's certificate.")
@click.option("--key", help="The server's private key.")
@click.option("--tls-key-passphrase-file", help="File holding the passphrase that decrypts --key.")
@click.option("--crl", help="CRL of the CA: revoked client certificates fail the handshake.")
@click.option("--issuer", help="Token issuer (iss).  [default: cryptoros-authz]")
@click.option("--audience", help="Token audience (aud).  [default: cryptoros]")
@click.option("--token-lifetime", type=int, help="Token lifetime in seconds.  [default: 300]")
@click.option("--probe", help="Loopback host:port serving /healthz and /metrics over plain HTTP, for probes "
                              "(no client certificate).")
@_with_passphrase
@click.option("--log-level", type=click.Choice(["debug", "info", "warning", "error"]), default="info",
              show_default=True)
@click.pass_context
def serve(ctx: click.Context, config_file: str | None, log_level: str, **flags) -> None:
    """Run the HTTPS token issuer (mutual TLS) until SIGTERM."""
    from authz_server.config import build_config, load_toml
    from authz_server.server import serve as run_server

    values: dict = load_toml(config_file) if config_file else {}
    root = ctx.find_root()
    source = root.get_parameter_source("db_url")
    values["db"], _db_from = serve_db(
        flag=root.obj["db"] if source == click.core.ParameterSource.COMMANDLINE else None,
        env=root.obj["db"] if source == click.core.ParameterSource.ENVIRONMENT else None,
        file=values.get("db"), config_file=config_file)
    mapping = {
        "host": "host", "port": "port", "ca": "ca", "cert": "cert", "key": "key",
        "tls_key_passphrase_file": "key_passphrase_file", "crl": "crl", "issuer": "issuer",
        "audience": "audience", "token_lifetime": "token_lifetime", "probe": "probe",
        "signing_key_passphrase_file": "signing_key_passphrase_file",
    }
    for flag, key in mapping.items():
        if flags.get(flag) is not None:
            values[key] = flags[flag]
    if flags.get("unsafe_no_passphrase"):
        values["unsafe_no_passphrase"] = True
    cfg = build_config(values)
    logfmt.configure(log_level, f"%(asctime)s {PROG}[%(process)d] %(levelname)s %(message)s", sys.stderr)
    logging.getLogger("alembic").setLevel(logging.WARNING)
    try:
        import uvloop  # type: ignore[import-not-found]

        runner = uvloop.run
    except ImportError:  # pragma: no cover
        import asyncio

        runner = asyncio.run
    try:
        runner(run_server(cfg))
    except KeyboardInterrupt:  # pragma: no cover - SIGINT before the handler is installed
        pass


if __name__ == "__main__":  # pragma: no cover
    main()
