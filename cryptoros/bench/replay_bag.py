"""The recorded sensor data of seed 002's replay, written with ``rosbags``: a rosbag of a
LaserScan topic at 10 Hz and a camera topic at 30 fps.

* ``/scan`` (sensor_msgs/LaserScan): the Hokuyo URG-04LX-UG01's 683 points over 240
  degrees, no intensities, frame ``laser``: 2,789 B on the wire. The paper reports
  4,152 B. Two layouts give exactly that with a 4-character frame id: 1,024 ranges and
  no intensities (the URG's 1,024 steps per revolution), or 683 ranges and 341
  intensities; both hold 1,024 floats. The paper says neither, so ``laser_ranges=1024``
  is offered as an option, not as its layout.
* ``/camera/image`` (sensor_msgs/CompressedImage, 640x480 JPEG): wire sizes drawn from
  the paper's reported mean and SD (79,736.9 B, 818.5 B). A raw 640x480 image cannot be
  80 KB, and sizes that vary are a compressed stream's; the JPEG bytes are random (a
  cipher's cost depends on the length only). ``image="raw"``: sensor_msgs/Image 640x480
  rgb8 instead (921,654 B), what the Xtion's raw topic carries: the hypothesis the
  stand-in's drop rates are checked against.
"""

from __future__ import annotations

from pathlib import Path

IMAGE_MEAN_B = 79_736.9
IMAGE_SD_B = 818.5
LASER_HZ = 10
IMAGE_HZ = 30
TOPICS = {"laser": ("/scan", "sensor_msgs/LaserScan", LASER_HZ), "image": ("/camera/image", "sensor_msgs/CompressedImage", IMAGE_HZ)}


def write_bag(path: Path, seconds: float, *, laser_ranges: int = 683, image: str = "compressed", seed: int = 2) -> dict:
    """Writes the bag; returns per topic the message count and wire sizes (mean, SD, min, max)."""
    import numpy as np
    from rosbags.rosbag1 import Writer

    from cryptoros.ros1 import msgs

    rng = np.random.default_rng(seed)
    store = msgs.typestore()
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = msgs.msg_class("std_msgs/Header")
    Scan = msgs.msg_class("sensor_msgs/LaserScan")
    Compressed = msgs.msg_class("sensor_msgs/CompressedImage")
    Raw = msgs.msg_class("sensor_msgs/Image")
    image_type = "sensor_msgs/CompressedImage" if image == "compressed" else "sensor_msgs/Image"
    topics = {**TOPICS, "image": ("/camera/image", image_type, IMAGE_HZ)}
    raw_pixels = rng.integers(0, 256, 640 * 480 * 3, dtype=np.uint8)
    t0_ns = 1_700_000_000 * 10**9
    frame = "laser" if laser_ranges == 683 else "base"
    span = 4.1888 if laser_ranges == 683 else 6.2832  # 240 degrees; 360 for a full revolution
    empty_image = len(msgs.serialize(Compressed(header=Header(seq=0, stamp=Time(sec=0, nanosec=0), frame_id="camera"),
                                                format="jpeg", data=np.zeros(0, np.uint8)), "sensor_msgs/CompressedImage"))
    sizes: dict[str, list[int]] = {"laser": [], "image": []}
    path.unlink(missing_ok=True)
    writer = Writer(path)
    writer.open()
    try:
        conns = {key: writer.add_connection(topic, msgs.store_name(typename), typestore=store,
                                            callerid="/hokuyo" if key == "laser" else "/camera")
                 for key, (topic, typename, _) in topics.items()}
        events = [(i * 10**9 // LASER_HZ, "laser", i) for i in range(int(seconds * LASER_HZ))]
        events += [(i * 10**9 // IMAGE_HZ, "image", i) for i in range(int(seconds * IMAGE_HZ))]
        events.sort()
        base = 2.0 + np.sin(np.linspace(0, 6, laser_ranges)).astype(np.float32)
        for offset, key, seq in events:
            t = t0_ns + offset
            header = Header(seq=seq, stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame if key == "laser" else "camera")
            if key == "laser":
                ranges = (base + rng.normal(0, 0.01, laser_ranges)).astype(np.float32)
                msg = Scan(header=header, angle_min=-span / 2, angle_max=span / 2, angle_increment=span / laser_ranges,
                           time_increment=0.1 / 1024, scan_time=0.1, range_min=0.02, range_max=5.6, ranges=ranges,
                           intensities=np.zeros(0, np.float32))
                raw = msgs.serialize(msg, "sensor_msgs/LaserScan")
            elif image == "raw":
                raw = msgs.serialize(Raw(header=header, height=480, width=640, encoding="rgb8", is_bigendian=0,
                                         step=640 * 3, data=np.roll(raw_pixels, seq)), "sensor_msgs/Image")
            else:
                n = int(round(rng.normal(IMAGE_MEAN_B, IMAGE_SD_B))) - empty_image
                msg = Compressed(header=header, format="jpeg", data=rng.integers(0, 256, max(n, 0), dtype=np.uint8))
                raw = msgs.serialize(msg, "sensor_msgs/CompressedImage")
            sizes[key].append(len(raw))
            writer.write(conns[key], t, raw)
    finally:
        writer.close()
    out = {}
    for key, values in sizes.items():
        arr = np.asarray(values, dtype=float)
        out[key] = {"topic": topics[key][0], "type": topics[key][1], "rate_hz": topics[key][2], "messages": len(values),
                    "bytes_mean": float(arr.mean()), "bytes_sd": float(arr.std()), "bytes_min": int(arr.min()),
                    "bytes_max": int(arr.max())}
    out["laser"]["ranges"] = laser_ranges
    return out


__all__ = ["IMAGE_HZ", "LASER_HZ", "TOPICS", "write_bag"]
