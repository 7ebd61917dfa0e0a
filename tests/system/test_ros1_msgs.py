"""Message types, serialization and md5sums (checked against ROS's own genpy)."""

from __future__ import annotations

import json

import pytest

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.ros1 import msgs
from tests.support import run

PINNED = {
    "std_msgs/String": "992ce8a1687cec8c8bd883ec73ca41d1",
    "std_msgs/Header": "2176decaecbce78abc3b96ef049fabed",
    "sensor_msgs/Image": "060021388200f6f0f447d0fcd9c64743",
    "geometry_msgs/Twist": "9f195f881246fdfa2798d1d3eebca84a",
    "nav_msgs/OccupancyGrid": "3381f2d731d4076ec5c71b0759edbe4e",
}


@pytest.mark.parametrize("name,md5", sorted(PINNED.items()))
def test_pinned_md5sums(name: str, md5: str) -> None:
    assert msgs.md5sum(name) == md5
    assert msgs.md5sum(msgs.store_name(name)) == md5


def test_md5sums_match_installed_ros() -> None:
    """Every listed type's md5sum equals the one genpy ships with Debian's ROS."""
    import shutil

    if shutil.which("rosmaster") is None:
        from tests.support import missing

        missing("ROS 1 python packages are not installed")
    names = [
        "std_msgs/String", "std_msgs/Header", "std_msgs/Float64MultiArray", "sensor_msgs/Image",
        "sensor_msgs/LaserScan", "sensor_msgs/PointCloud2", "geometry_msgs/PoseStamped",
        "geometry_msgs/Twist", "std_msgs/Empty", "std_msgs/Time",
    ]
    code = (
        "import importlib, json, sys\n"
        "out = {}\n"
        "for n in sys.argv[1:]:\n"
        "    p, t = n.split('/')\n"
        "    c = getattr(importlib.import_module(p + '.msg'), t)\n"
        "    out[n] = [c._md5sum, c._type]\n"
        "print(json.dumps(out))\n"
    )
    res = run(["/usr/bin/python3", "-c", code, *names], timeout=30, check=True)
    ros = json.loads(res.stdout)
    for name in names:
        assert msgs.md5sum(name) == ros[name][0], name
        assert msgs.ros1_name(msgs.store_name(name)) == ros[name][1]


def test_roundtrip_string_and_image() -> None:
    S = msgs.msg_class("std_msgs/String")
    data = msgs.serialize(S(data="héllo"), "std_msgs/String")
    assert data == b"\x06\x00\x00\x00h\xc3\xa9llo"
    assert msgs.deserialize(data, "std_msgs/msg/String").data == "héllo"

    import numpy as np

    st = msgs.typestore()
    Header = msgs.msg_class("std_msgs/Header")
    Time = st.types["builtin_interfaces/msg/Time"]
    Image = msgs.msg_class("sensor_msgs/Image")
    img = Image(
        header=Header(seq=7, stamp=Time(sec=1, nanosec=2), frame_id="cam"),
        height=2, width=3, encoding="rgb8", is_bigendian=0, step=9,
        data=np.arange(18, dtype=np.uint8),
    )
    raw = msgs.serialize(img, "sensor_msgs/Image")
    back = msgs.deserialize(raw, "sensor_msgs/Image")
    assert back.header.seq == 7 and back.header.frame_id == "cam"
    assert bytes(back.data) == bytes(range(18))


def test_custom_types_registered_at_run_time() -> None:
    extra = {"my_pkg/Foo": "Header header\nint32 x\nstring[] names\n", "my_pkg/msg/Bar": "my_pkg/Foo[] foos\n"}
    st = msgs.typestore(extra)
    assert st is msgs.typestore(dict(reversed(list(extra.items()))))
    assert st is not msgs.typestore()
    # genmsg: md5 of "<md5 of Header> header\nint32 x\nstring[] names"
    assert msgs.md5sum("my_pkg/Foo", st) == "8ee24171a142fddecdc4ce1af5057cd5"
    text = msgs.message_definition("my_pkg/Bar", st)
    assert "MSG: my_pkg/Foo" in text and "MSG: std_msgs/Header" in text
    Foo = msgs.msg_class("my_pkg/Foo", st)
    Header = msgs.msg_class("std_msgs/Header", st)
    Time = st.types["builtin_interfaces/msg/Time"]
    foo = Foo(header=Header(seq=1, stamp=Time(sec=0, nanosec=0), frame_id=""), x=-5, names=["a", "b"])
    assert msgs.deserialize(msgs.serialize(foo, "my_pkg/Foo", st), "my_pkg/Foo", st).names == ["a", "b"]
    with pytest.raises(LocalProtocolError):
        msgs.md5sum("my_pkg/Foo")  # not in the plain store


def test_errors_are_typed() -> None:
    with pytest.raises(RemoteProtocolError):
        msgs.deserialize(b"\xff\xff\xff\x7f", "std_msgs/String")
    with pytest.raises(RemoteProtocolError):
        msgs.deserialize(b"\x01\x00\x00\x00ab", "std_msgs/String")  # trailing byte
    with pytest.raises(LocalProtocolError):
        msgs.md5sum("nope/Nothing")
    with pytest.raises(LocalProtocolError):
        msgs.ros1_name("not a type")
    with pytest.raises(LocalProtocolError):
        msgs.typestore({"x/Bad": "int32 x=\n"})
    assert msgs.ros1_name("std_msgs/msg/String") == "std_msgs/String"
