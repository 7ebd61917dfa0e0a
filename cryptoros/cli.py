"""``cryptoros``: the umbrella command.

Subcommands live in the modules that own them and are imported only when used, so
``cryptoros --help`` stays fast and one broken optional part cannot take the others
down. A subcommand is listed here only once it exists.
"""

from __future__ import annotations

import click

from cryptoros.lazy import LazyGroup

# name -> "module:attribute" of a click command or group
SUBCOMMANDS: dict[str, str] = {
    "master": "cryptoros.ros1.cli:master",
    "sim": "cryptoros.sim.cli:sim",
    "bench": "cryptoros.bench:bench",
    "demo": "cryptoros.demo.cli:demo",
    "attack": "cryptoros.attack.cli:attack",
    "status": "interceptor.status:status",
    "monitor": "cryptoros.monitor.cli:monitor",
}


@click.group(cls=LazyGroup, subcommands=SUBCOMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="cryptoros")
def main() -> None:
    """cryptoros: secure ROS robot communication without touching robot code."""


if __name__ == "__main__":  # pragma: no cover
    main()
