"""``cryptoros bench``: benchmarks that print figures side by side in one run.

Speed is measured here, never asserted in timed tests. Each benchmark is its own
module, imported only when run.
"""

from __future__ import annotations

import click

from cryptoros.lazy import LazyGroup

BENCHMARKS: dict[str, str] = {
    "authz": "cryptoros.bench.authz:authz",
    "fleet": "cryptoros.bench.fleet:fleet",
    "ciphers": "cryptoros.bench.ciphers:ciphers",
    "cipher-replay": "cryptoros.bench.replay:cipher_replay",
    "insider": "cryptoros.bench.insider:insider",
    "monitor": "cryptoros.bench.monitor:monitor",
    "interceptor": "cryptoros.bench.interceptor:interceptor",
    "ros1": "cryptoros.bench.ros1:ros1",
    "ros2": "cryptoros.bench.ros2:ros2",
    "ros2-insider": "cryptoros.bench.ros2_insider:ros2_insider",
    "scale": "cryptoros.bench.scale:scale",
    "sim": "cryptoros.bench.sim:sim",
    "soak": "cryptoros.bench.soak:soak",
}


@click.group(cls=LazyGroup, subcommands=BENCHMARKS)
def bench() -> None:
    """Benchmarks: token issuing, a fleet against authz replicas, ROS 1 transport, cipher costs, simulator scale, an interceptor's growth with streams and topics."""
