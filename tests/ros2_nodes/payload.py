"""Deterministic message contents for the ROS 2 test nodes (rclpy message types only)."""

from geometry_msgs.msg import Twist
from sensor_msgs.msg import Image, LaserScan
from std_msgs.msg import String

TYPES = {"string": String, "twist": Twist, "scan": LaserScan, "image": Image}
NAMES = {
    "string": "std_msgs/msg/String",
    "twist": "geometry_msgs/msg/Twist",
    "scan": "sensor_msgs/msg/LaserScan",
    "image": "sensor_msgs/msg/Image",
}
_PATTERN = bytes(range(256)) * 321
IMAGE_W, IMAGE_H = 160, 128  # rgba8: 81920 bytes


def make(kind: str, seq: int):
    if kind == "string":
        return String(data=f"secret-{seq}")
    if kind == "twist":
        m = Twist()
        m.linear.x, m.linear.y, m.angular.z = float(seq), -0.25 * seq, 0.5 * seq
        return m
    if kind == "scan":
        m = LaserScan()
        m.header.frame_id = f"scan-{seq}"
        m.angle_min, m.angle_max, m.angle_increment = -3.14, 3.14, 0.0175
        m.range_min, m.range_max = 0.1, 30.0
        m.ranges = [seq + i * 0.01 for i in range(360)]
        m.intensities = [float(i % 7) for i in range(360)]
        return m
    m = Image()
    m.header.frame_id = f"image-{seq}"
    m.width, m.height, m.encoding, m.step = IMAGE_W, IMAGE_H, "rgba8", IMAGE_W * 4
    shift = seq % 256
    m.data = _PATTERN[shift : shift + IMAGE_W * IMAGE_H * 4]
    return m


def seq_of(kind: str, msg) -> int:
    if kind == "string":
        return int(msg.data.rsplit("-", 1)[1])
    if kind == "twist":
        return int(msg.linear.x)
    return int(msg.header.frame_id.rsplit("-", 1)[1])


def intact(kind: str, msg) -> bool:
    seq = seq_of(kind, msg)
    expected = make(kind, seq)
    if kind == "image":
        return bytes(msg.data) == bytes(expected.data) and (msg.width, msg.height, msg.encoding) == (
            expected.width, expected.height, expected.encoding)
    if kind == "scan":
        return list(msg.ranges) == list(expected.ranges) and list(msg.intensities) == list(expected.intensities)
    return msg == expected
