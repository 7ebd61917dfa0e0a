"""``cryptoros-authz learn`` (start, stop, status, propose, apply) and ``unused``: least
privilege from what a robot really does. ``authz_server.cli`` registers them.

Learning mode is started only here, by whoever can write the registry; no interceptor
and no certificate can start it (the daemon has no endpoint for it). The proposal
logic is :mod:`authz_server.learning`.
"""

from __future__ import annotations

import re
import time
from datetime import UTC, datetime

import click

from authz_server.changes import parse_since
from authz_server.learning import known_types, proposal_diff, proposal_yaml, propose, unused
from authz_server.cli_context import registry as _registry
from authz_server.policy_cli import write_or_print
from authz_server.registry import MAX_LEARNING_S, Registry
from cryptoros.errors import RegistryError

PROG = "cryptoros-authz"
_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([smhd]?)\s*$")
_UNITS = {"": 1, "s": 1, "m": 60, "h": 3600, "d": 86400}


def parse_duration(text: str) -> float:
    """``30m``, ``2h``, ``90s``, ``90`` (seconds)."""
    m = _DURATION.match(text)
    if not m:
        raise click.BadParameter(f"{text!r}: expected a duration such as 30m, 2h or 90s", param_hint="--for")
    return float(m.group(1)) * _UNITS[m.group(2)]


def _when(at: float | None) -> str:
    return "-" if at is None else datetime.fromtimestamp(at, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _since(text: str | None) -> float | None:
    if text is None:
        return None
    try:
        return parse_since(text).timestamp()
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--since") from None


@click.group("learn")
def learn() -> None:
    """Learning mode: let a manager's robots run, record what its nodes need, propose the grants."""


@learn.command("start")
@click.argument("manager")
@click.option("--for", "duration", default="30m", show_default=True, metavar="DURATION",
              help=f"How long (30m, 2h, 90s; at most {MAX_LEARNING_S // 3600} h). It ends by itself.")
@click.pass_context
def start(ctx: click.Context, manager: str, duration: str) -> None:
    """Put MANAGER in learning mode: its own nodes' requests that no grant covers are let
    through and recorded, and let through to and from other managers only while they
    learn too. Certificates, tokens, revocation, dropped shutdowns and strangers are
    checked as always."""
    seconds = parse_duration(duration)
    since, until = _registry(ctx).set_learning(manager, seconds)
    click.echo(f"{manager}: LEARNING from {_when(since)} until {_when(until)} ({seconds:g} s); every interceptor "
               f"of {manager} says so in its log and status within one feed poll. Then: {PROG} learn propose {manager}")


@learn.command("stop")
@click.argument("manager")
@click.pass_context
def stop(ctx: click.Context, manager: str) -> None:
    """End MANAGER's learning window now (streams only it allowed are cut)."""
    reg = _registry(ctx)
    _since_at, until = reg.learning_window(manager)
    if until is None or until <= time.time():
        click.echo(f"{manager}: not learning (nothing changed)")
        return
    reg.set_learning(manager, None)
    click.echo(f"{manager}: learning mode ended; requests no grant covers are refused again")


@learn.command("status")
@click.argument("manager", required=False)
@click.pass_context
def status(ctx: click.Context, manager: str | None) -> None:
    """Each manager's learning window and how many requests it recorded."""
    reg = _registry(ctx)
    now = time.time()
    names = [manager] if manager else [m.name for m in reg.list_managers()]
    for name in names:
        since, until = reg.learning_window(name)
        learned = reg.observations(name, allowed=False)
        state = "LEARNING" if until is not None and until > now else "enforcing"
        window = f", window {_when(since)} to {_when(until)}" if since is not None else ""
        left = f" ({until - now:.0f} s left)" if state == "LEARNING" else ""
        click.echo(f"{name}: {state}{left}{window}; {len(learned)} distinct requests recorded")


def _proposal(reg: Registry, manager: str, since: float | None):
    info = reg.get_manager(manager)
    learned = reg.observations(manager, allowed=False, since=since)
    every = reg.observations()
    all_grants = [g for m in reg.list_managers() for g in m.grants]
    return info, propose(manager, learned, info.grants, known_types(every, all_grants)), learned


@learn.command("propose")
@click.argument("manager")
@click.option("--since", metavar="AGE|TIME", help="Only requests seen since then (7d, 2h, or an ISO time).")
@click.option("-o", "--output", type=str, help="Write the proposal (import YAML) to this file; the diff goes "
                                               "to stderr.")
@click.pass_context
def propose_cmd(ctx: click.Context, manager: str, since: str | None, output: str | None) -> None:
    """Print the smallest grants that would have allowed what MANAGER's nodes did while
    learning: the import YAML (each grant with its count and last use), then the diff
    against the current policy. Nothing is changed: review it, then `learn apply`."""
    info, proposal, learned = _proposal(_registry(ctx), manager, _since(since))
    write_or_print(output, proposal_yaml(proposal))
    err = output is not None
    click.echo(f"# {manager}: {len(learned)} requests recorded, {len(proposal.grants)} grants proposed, "
               f"{len(info.grants)} held now", err=err)
    for line in proposal_diff(proposal, info.grants):
        click.echo(f"# {line}", err=err)
    for note in proposal.notes:
        click.echo(f"{PROG}: learn: {note}", err=True)


@learn.command("apply")
@click.argument("manager")
@click.option("--since", metavar="AGE|TIME", help="Only requests seen since then (as for propose).")
@click.option("--yes", is_flag=True, help="Apply without asking.")
@click.pass_context
def apply(ctx: click.Context, manager: str, since: str | None, yes: bool) -> None:
    """Add the proposed grants to MANAGER (one recorded change; `audit --changes` shows it)."""
    reg = _registry(ctx)
    info, proposal, _learned = _proposal(reg, manager, _since(since))
    if not proposal.grants:
        click.echo(f"{manager}: nothing to apply (every request seen is granted already)")
        return
    for line in proposal_diff(proposal, ()):
        click.echo(line)
    for note in proposal.notes:
        click.echo(f"{PROG}: learn: {note}", err=True)
    if not yes and not click.confirm(f"add these {len(proposal.grants)} grants to {manager}?", err=True):
        raise RegistryError("not applied")
    added = reg.grant_many(manager, [p.grant for p in proposal.grants])
    click.echo(f"{manager}: {sum(added)} grants added ({len(info.grants) + sum(added)} in all)")


@click.command("unused")
@click.option("--since", default="7d", show_default=True, metavar="AGE|TIME",
              help="The window: grants no request used since then are listed.")
@click.option("--manager", help="Only this manager.")
@click.pass_context
def unused_cmd(ctx: click.Context, since: str, manager: str | None) -> None:
    """List the grants no request used since --since (reported by the interceptors), for
    removal: least privilege kept, not only reached. Exit 0 either way."""
    reg = _registry(ctx)
    since_at = _since(since)
    managers = [reg.get_manager(manager)] if manager else reg.list_managers()
    total = 0
    for info in managers:
        for g in unused(info.grants, reg.observations(info.name, allowed=True, since=since_at)):
            total += 1
            type_ = "" if g.action in ("read_param", "write_param") else f" {g.type}"
            click.echo(f"{info.name} {g.action} {g.node} {g.name}{type_}  "
                       f"(remove: {PROG} revoke {info.name} {g.action} {g.node} {g.name})")
    click.echo(f"# {total} grants unused since {_when(since_at)}", err=True)


COMMANDS = (learn, unused_cmd)

__all__ = ["COMMANDS", "learn", "parse_duration", "unused_cmd"]
