"""``cryptoros bench ros2``'s CPU accounting, without ROS 2: /proc readers and the per-message arithmetic."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cryptoros.bench import ros2 as bench

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")


def test_cpu_seconds_and_children_come_from_proc():
    start = bench.cpu_seconds(os.getpid())
    deadline = time.process_time() + 0.05
    while time.process_time() < deadline:
        pass
    assert start is not None and bench.cpu_seconds(os.getpid()) >= start
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(10)"])
    try:
        assert child.pid in bench.children(os.getpid())
    finally:
        child.kill()
        child.wait(timeout=10)
    assert bench.cpu_seconds(2**22 + 12345) is None  # no such process


def test_cpu_per_message_totals_and_pipeline_ceiling():
    result = {"received": 1000, "pub_cpu_s": 0.020, "sub_cpu_s": 0.010}
    before = {"interceptor_a": 1.0, "bridge_a": 2.0, "interceptor_b": 3.0, "bridge_b": 4.0, "_t": 10.0}
    after = {"interceptor_a": 1.005, "bridge_a": 2.030, "interceptor_b": 3.004, "bridge_b": 4.025, "_t": 11.0}
    bridged = bench.cpu_per_message(result, before, after, bridged=True)
    assert bridged["us_per_msg"] == {"publisher": 20.0, "interceptor_a": 5.0, "bridge_a": 30.0,
                                     "interceptor_b": 4.0, "bridge_b": 25.0, "subscriber": 10.0}
    assert bridged["total_us"] == 94.0 and bridged["busiest"] == "bridge_a"
    assert bridged["ceiling_msg_s"] == round(1e6 / 30.0) and bridged["window_s"] == 1.0
    direct = bench.cpu_per_message(result, before, after, bridged=False)  # the idle pair is shown, not counted
    assert direct["total_us"] == 30.0 and direct["ceiling_msg_s"] == 50_000 and direct["busiest"] == "publisher"


def test_bench_ros2_insider_prints_the_depth_attack_and_burst_figures():
    """``cryptoros bench ros2-insider`` on small numbers: it runs against the real pair and
    prints robot B's RSS rows and the burst's delivery (every frame of a burst larger
    than the bucket arrives: throttled, never stalled)."""
    from tests.ros2_support import ros2_python

    python = ros2_python()
    r = subprocess.run([str(Path(sys.executable).parent / "cryptoros"), "bench", "ros2-insider", "--depth-samples", "20",
                        "--sample-kib", "64", "--burst", "300", "--rate", "200", "--python", str(python)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "interceptor_b" in r.stdout and "bridge_b" in r.stdout
    assert "delivered to robot B's listener: 360 of 360" in r.stdout, r.stdout[-1500:]
