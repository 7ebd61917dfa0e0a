"""``cryptoros``: the umbrella command.

Subcommands live in the modules that own them and are imported only when used, so
``cryptoros --help`` stays fast and one broken optional part cannot take the others
down. A subcommand is listed here only once it exists.
"""

from __future__ import annotations

import importlib
import importlib.util

import click

# name -> "module:attribute" of a click command or group
SUBCOMMANDS: dict[str, str] = {
    "master": "cryptoros.ros1.cli:master",
    "sim": "cryptoros.sim.cli:sim",
    "bench": "cryptoros.bench:bench",
    "demo": "cryptoros.demo.cli:demo",
    "attack": "cryptoros.attack.cli:attack",
}


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
        self.subcommands = SUBCOMMANDS if subcommands is None else subcommands

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(_available(self.subcommands)))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = _available(self.subcommands).get(cmd_name)
        if target is None:
            return super().get_command(ctx, cmd_name)
        module_name, attr = target.split(":", 1)
        return getattr(importlib.import_module(module_name), attr)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="cryptoros")
def main() -> None:
    """cryptoros: secure ROS robot communication without touching robot code."""


if __name__ == "__main__":  # pragma: no cover
    main()
