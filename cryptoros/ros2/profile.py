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
from xml.etree import ElementTree

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


#: the most samples a KEEP_ALL reader or writer of the bridge holds (Fast DDS's default is
#: 5,000). With a backlog near 5,000, every message costs both ends 2 to 2.5 times the CPU,
#: and a publisher that keeps up with the reader keeps the backlog there: measured on the
#: direct path (one rclpy publisher and subscriber, 20,000 Strings at full speed, the
#: subscriber paused 0.3 s once), 21 to 25 us per message at each end against 7 to 10
#: unpaused, and one-way p50 280 to 315 ms; with both ends capped at 1,000, 8 to 10 us and
#: 1.2 to 1.4 ms after the same pause, and the same 75,000 to 81,000 messages a second
#: unpaused (capped at 256: 36,000, the writer waiting on acknowledgements).
BRIDGE_MAX_SAMPLES = 1000

_DDS_NS = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"


def write_bridge_profile(directory: Path, max_samples: int = BRIDGE_MAX_SAMPLES) -> Path:
    """Write the bridge's profile into ``directory`` and return its path: the localhost
    profile, with every reader and writer (the default profiles) holding at most
    ``max_samples`` samples. The robot's own nodes keep the localhost profile as it is."""
    ElementTree.register_namespace("", _DDS_NS)
    tree = ElementTree.parse(LOCALHOST_PROFILE)  # our own file, not input
    profiles = tree.getroot().find(f"{{{_DDS_NS}}}profiles")
    writer = profiles.find(f"{{{_DDS_NS}}}data_writer") if profiles is not None else None
    if writer is None:
        raise ValueError(f"{LOCALHOST_PROFILE} has no default data_writer profile")
    reader = ElementTree.SubElement(profiles, f"{{{_DDS_NS}}}data_reader",
                                    {"profile_name": "cryptoros_bridge_reader", "is_default_profile": "true"})
    for entity in (writer, reader):
        topic = ElementTree.Element(f"{{{_DDS_NS}}}topic")
        limits = ElementTree.SubElement(topic, f"{{{_DDS_NS}}}resourceLimitsQos")
        for name, value in (("max_samples", max_samples), ("max_instances", 1),
                            ("max_samples_per_instance", max_samples), ("allocated_samples", min(max_samples, 100))):
            ElementTree.SubElement(limits, f"{{{_DDS_NS}}}{name}").text = str(value)
        entity.insert(0, topic)  # the schema wants <topic> before <times>
    ElementTree.indent(tree, space="  ")
    path = Path(directory) / "bridge_profile.xml"
    tree.write(path, encoding="UTF-8", xml_declaration=True)
    return path


__all__ = ["BRIDGE_MAX_SAMPLES", "LOCALHOST_PROFILE", "PROFILE_ENV", "environment_problem", "localhost_env",
           "segments_cleaned", "shm_clean_command", "write_bridge_profile"]
