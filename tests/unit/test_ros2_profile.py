"""The bridge's Fast DDS profile, derived from the robot's localhost profile."""

from __future__ import annotations

import tempfile
from types import SimpleNamespace
from xml.etree import ElementTree

import pytest

from cryptoros.errors import CryptorosError
from cryptoros.ros2.profile import (BRIDGE_MAX_SAMPLES, LOCALHOST_PROFILE, PROFILE_ENV, environment_problem,
                                    write_bridge_profile)
from interceptor.ros2_bridge import DdsBridge

NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def _limits(entity: ElementTree.Element) -> dict[str, int]:
    limits = entity.find(f"{NS}topic/{NS}resourceLimitsQos")
    assert limits is not None
    return {child.tag.removeprefix(NS): int(child.text or "") for child in limits}


def test_the_bridge_profile_caps_every_default_reader_and_writer_and_keeps_the_rest(tmp_path):
    before = LOCALHOST_PROFILE.read_text()
    path = write_bridge_profile(tmp_path)
    assert LOCALHOST_PROFILE.read_text() == before  # the robot's own profile is left as it is
    assert environment_problem({PROFILE_ENV: str(path)}) is None  # still DDS on 127.0.0.1 and shared memory only
    profiles = ElementTree.parse(path).getroot().find(f"{NS}profiles")
    assert profiles is not None
    writers = [e for e in profiles.findall(f"{NS}data_writer") if e.get("is_default_profile") == "true"]
    readers = [e for e in profiles.findall(f"{NS}data_reader") if e.get("is_default_profile") == "true"]
    assert len(writers) == len(readers) == 1
    for entity in (writers[0], readers[0]):
        assert _limits(entity) == {"max_samples": BRIDGE_MAX_SAMPLES, "max_instances": 1,
                                   "max_samples_per_instance": BRIDGE_MAX_SAMPLES, "allocated_samples": 100}
        assert entity[0].tag == f"{NS}topic"  # the schema's order: <topic> before <times>
    assert writers[0].find(f"{NS}times/{NS}heartbeatPeriod/{NS}nanosec").text == "100000000"
    assert profiles.find(f"{NS}transport_descriptors") is not None


def test_writing_the_bridge_profile_again_gives_the_same_file(tmp_path):
    first = write_bridge_profile(tmp_path).read_bytes()
    assert write_bridge_profile(tmp_path).read_bytes() == first


def test_a_bridge_whose_profile_cannot_be_written_fails_with_one_clear_line(monkeypatch, tmp_path):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "missing"))
    bridge = DdsBridge(SimpleNamespace(domain_id=7), lambda *_: None, lambda *_: None)
    with pytest.raises(CryptorosError, match=r"cannot write the DDS bridge's profile into .*missing: No such file"):
        bridge._env()


def test_a_bridge_runs_with_the_bridge_profile_in_its_domain(monkeypatch, tmp_path):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    bridge = DdsBridge(SimpleNamespace(domain_id=7), lambda *_: None, lambda *_: None)
    env = bridge._env()
    assert env["ROS_DOMAIN_ID"] == "7" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert env[PROFILE_ENV].endswith("bridge_profile.xml") and environment_problem(env) is None
    assert env[PROFILE_ENV] == bridge._env()[PROFILE_ENV]  # one file per bridge, written again on a restart
    assert env[PROFILE_ENV].startswith(str(tmp_path))
