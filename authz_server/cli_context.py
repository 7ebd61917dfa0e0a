"""What every ``cryptoros-authz`` verb opens the same way: the registry named by the root
group's ``--db``, its changes recorded with the command line as typed."""

from __future__ import annotations

import shlex
import sys

import click

from authz_server.changes import ChangeSource
from authz_server.db import open_registry
from authz_server.registry import Registry

PROG = "cryptoros-authz"


def registry(ctx: click.Context, *, create: bool = False) -> Registry:
    """The registry of the root group's ``--db``, closed with the command."""
    engine = open_registry(ctx.find_root().obj["db"], create=create)
    ctx.call_on_close(engine.dispose)
    return Registry(engine, source=ChangeSource.here(command_line(ctx)))


def command_line(ctx: click.Context) -> str:
    """The command a change is recorded with: the verb and its arguments as typed,
    without the group's options (``--db`` may hold a password)."""
    verb = ctx.command_path.split()[1:2]
    args = sys.argv[1:]
    i = 0
    while i < len(args) and args[i].startswith("-"):
        i += 2 if args[i] == "--db" else 1
    if verb and args[i:i + 1] == verb:
        return shlex.join([PROG, *args[i:]])
    return ctx.command_path  # run in-process (not from a command line)


__all__ = ["command_line", "registry"]
