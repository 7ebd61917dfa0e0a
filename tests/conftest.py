"""Shared fixtures. The throwaway PKI fixtures live in tests/pki_fixtures.py."""

import hashlib
import os
from pathlib import Path

import pytest

from tests.support import require, run

pytest_plugins = ["tests.pki_fixtures"]

#: Modules whose tests run one after another on one xdist worker (``--dist loadgroup``,
#: scripts/test): whole missions, benchmarks and rate or deadline checks that must not
#: share the two cores with another of their kind. The other tests fill the other worker.
HEAVY_MODULES = {
    "test_demo", "test_ros2_demo", "test_runbook", "test_bench_ros2", "test_bench_interceptor", "test_bench_soak",
    "test_monitor_dataset", "test_monitor_live", "test_stock_tools", "test_ros2", "test_ros2_hardening",
    "test_interceptor_operations", "test_day2_live", "test_bench_fleet",
}


def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in HEAVY_MODULES:
            item.add_marker(pytest.mark.xdist_group("heavy"))

ROS1_NODES = Path(__file__).parent / "ros1_nodes"


@pytest.fixture(scope="module")
def roscpp_talker(request) -> str:
    """Debian's roscpp talker (tests/ros1_nodes/talker.cpp), compiled once and cached."""
    require("g++", "pkg-config")
    src = ROS1_NODES / "talker.cpp"
    flags = run(["pkg-config", "--cflags", "--libs", "roscpp", "std_msgs"], timeout=10)
    if flags.returncode != 0:
        from tests.support import missing

        missing("roscpp development files are not installed (libroscpp-dev)")
    digest = hashlib.sha256(src.read_bytes() + flags.stdout.encode()).hexdigest()[:16]
    out = Path(request.config.cache.mkdir("ros1_roscpp")) / f"talker-{digest}"
    if not out.exists():
        tmp = out.with_suffix(f".{os.getpid()}.tmp")  # two workers may compile at once
        run(["g++", "-O2", "-o", str(tmp), str(src), *flags.stdout.split()], timeout=180, check=True)
        tmp.rename(out)
    return str(out)
