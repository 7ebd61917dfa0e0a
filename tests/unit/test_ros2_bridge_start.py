"""DdsBridge.start: a bridge whose process exits before its hello is an error at once,
not after BRIDGE_START_TIMEOUT (ROS 2 audit: a broken bridge python cost 30 s per try,
and the flows came back 33 s after it was fixed)."""

from __future__ import annotations

import asyncio
import time
from types import SimpleNamespace

import pytest

from cryptoros.errors import CryptorosError
from interceptor.ros2_bridge import BRIDGE_START_TIMEOUT, DdsBridge


def test_a_bridge_that_exits_at_once_is_an_error_at_once(tmp_path):
    broken = tmp_path / "python"
    broken.write_text("#!/bin/sh\necho 'no rclpy here' >&2\nexit 3\n")
    broken.chmod(0o755)
    settings = SimpleNamespace(python=broken, domain_id=77, node_name="cryptoros_bridge", graph_interval=0.5,
                               max_message_size=1 << 20)
    bridge = DdsBridge(settings, lambda *_: None, lambda *_: None)

    async def attempt() -> float:
        started = time.monotonic()
        with pytest.raises(CryptorosError, match="exited with status 3 before it was up"):
            await bridge.start()
        return time.monotonic() - started

    took = asyncio.run(attempt())
    assert took < BRIDGE_START_TIMEOUT / 2 and not bridge.ready
