"""Shared fixtures. The throwaway PKI fixtures live in tests/pki_fixtures.py."""

import hashlib
import os
from pathlib import Path

import pytest

from cryptoros.lab.processes import PORT_SLICE_ENV
from tests.support import require, run

pytest_plugins = ["tests.pki_fixtures", "tests.scheduling"]

ROS1_NODES = Path(__file__).parent / "ros1_nodes"

# Each test worker's labs pick their ports in a slice of their own: two workers' labs
# once picked the same port (cryptoros/lab/processes.py, free_port).
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
if _WORKER.startswith("gw") and _WORKER[2:].isdigit():
    os.environ.setdefault(PORT_SLICE_ENV, f"{int(_WORKER[2:])}/{os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1')}")


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


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    """``cryptoros-authz serve`` as a real subprocess, one per test module, serving
    :func:`tests.authz_support.build_team`'s registry (``daemon.team``)."""
    from tests.authz_support import AuthzDaemon, build_team

    team = build_team(tmp_path_factory.mktemp("authz-daemon"))
    d = AuthzDaemon(pki=team.pki, db=team.db, workdir=team.workdir)
    try:
        d.start()
        d.team = team
        yield d
    finally:
        d.stop()
