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
    "denials": "interceptor.status:denials",
    "unquarantine": "interceptor.status:unquarantine",
    "env": "interceptor.runenv:env",
    "run": "interceptor.runenv:run",
}
MONITOR_SUBCOMMANDS: dict[str, str] = {
    "record": "cryptoros.monitor.cli:record",
    "train": "cryptoros.monitor.cli:train",
    "eval": "cryptoros.monitor.cli:evaluate",
    "dataset": "cryptoros.demo.dataset:dataset",
}


@click.group(cls=LazyGroup, subcommands=SUBCOMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="cryptoros")
def main() -> None:
    """cryptoros: secure ROS robot communication without touching robot code."""


@main.group(cls=LazyGroup, subcommands=MONITOR_SUBCOMMANDS)
def monitor() -> None:
    """The runtime monitor: record labelled datasets, train its model on clean recordings,
    evaluate it on attacks.

    Recordings are ROS 1 bags (`monitor record`, `monitor dataset`); the interceptor
    loads the model named in its [monitor] section (docs/monitor.md)."""


if __name__ == "__main__":  # pragma: no cover
    main()
