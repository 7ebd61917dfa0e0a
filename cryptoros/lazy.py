"""A click group whose subcommands live in the modules that own them, imported on first
use (``cryptoros`` and ``cryptoros bench``): ``--help`` stays fast and one broken
optional part cannot take the others down."""

from __future__ import annotations

import importlib
import importlib.util

import click


def _available(subcommands: dict[str, str]) -> dict[str, str]:
    found = {}
    for name, target in subcommands.items():
        module_name = target.split(":", 1)[0]
        try:
            spec = importlib.util.find_spec(module_name)
        except ModuleNotFoundError:
            spec = None
        if spec is not None:
            found[name] = target
    return found


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def __init__(self, *args, subcommands: dict[str, str] | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.subcommands = subcommands or {}

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(_available(self.subcommands)))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = _available(self.subcommands).get(cmd_name)
        if target is None:
            return super().get_command(ctx, cmd_name)
        module_name, attr = target.split(":", 1)
        return getattr(importlib.import_module(module_name), attr)


__all__ = ["LazyGroup"]
