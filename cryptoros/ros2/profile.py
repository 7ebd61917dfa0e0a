"""The Fast DDS profile that keeps a robot's DDS domain private to its host.

``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` stops a participant announcing itself to
other hosts, but it still binds its UDP sockets to every interface and answers unicast
discovery from anyone who names its address as a static peer (measured: a stranger on
another host read the robot's topics). The profile here replaces Fast DDS's built-in
transports with UDP on 127.0.0.1 and shared memory only. Every participant cryptoros
starts (the bridge, the demo's ROS 2 robots) uses it; operators point their own nodes
at it with ``FASTRTPS_DEFAULT_PROFILES_FILE`` (``cryptoros-interceptor --ros2-profile``
writes a copy).
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Mapping
from pathlib import Path

PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
LOCALHOST_PROFILE = Path(__file__).with_name("localhost_profile.xml")
_MARKER = "<address>127.0.0.1</address>"
_CLEANED = re.compile(r"(\d+) zombie segments cleaned")


def localhost_env(env: dict[str, str]) -> dict[str, str]:
    """``env`` with the localhost-only profile in force."""
    return {**env, PROFILE_ENV: str(LOCALHOST_PROFILE)}


def environment_problem(environ: dict[str, str] | None = None) -> str | None:
    """Why nodes started from this environment would answer other hosts, or None."""
    environ = os.environ if environ is None else environ
    path = environ.get(PROFILE_ENV)
    if not path:
        return f"{PROFILE_ENV} is not set"
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        return f"{PROFILE_ENV}={path}: {exc.strerror}"
    if _MARKER not in text or "<useBuiltinTransports>false</useBuiltinTransports>" not in text:
        return f"{PROFILE_ENV}={path} does not restrict DDS to 127.0.0.1"
    return None


__all__ = ["LOCALHOST_PROFILE", "PROFILE_ENV", "environment_problem", "localhost_env"]


def shm_clean_command(python: str | os.PathLike[str], environ: Mapping[str, str]) -> list[str] | None:
    """eProsima's ``fastdds shm clean`` (beside the ROS 2 ``python``, as in a venv's or
    ``/opt/ros/<distro>``'s ``bin/``, else on ``PATH``), or None if neither has it. It
    removes the shared-memory files of DDS processes that died without closing them (a
    SIGKILL, a crash): a live process holds a lock on each of its files, and until someone
    removes a dead one's, they hold memory in /dev/shm."""
    beside = Path(python).parent / "fastdds"
    tool = str(beside) if beside.is_file() else shutil.which("fastdds", path=environ.get("PATH"))
    return [tool, "shm", "clean"] if tool else None


def segments_cleaned(report: str) -> int:
    """How many dead processes' segments ``fastdds shm clean`` said it removed (0 if it
    did not say)."""
    found = _CLEANED.search(report)
    return int(found.group(1)) if found else 0
