"""One peer's unfinished ROS 2 frames, across all its streams to this robot.

A frame's head says how long its body is; until the body is all there, the stream's
decoder holds it. Every stream a peer keeps here (a topic it publishes, a service it
serves, the calls it makes to a service of ours) can hold one such frame of up to
``[ros2] max_message_size``. :class:`PartialFrames` keeps the sum per peer manager and
refuses the stream that would take it over the limit (``partial_frames``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from cryptoros.errors import PolicyDenied

#: bytes of unfinished frames (a frame's header read, its body not all there yet) one peer
#: may make this robot hold across all its streams, in max_message_size units: an insider
#: that announced 16 MiB frames on 80 streams and sent all but their last bytes held
#: 1.4 GB here, and nothing ended it
PARTIAL_FRAMES_PER_PEER = 4


class PartialFrames:
    """Bytes of unfinished frames held per peer manager (pure bookkeeping, no I/O)."""

    def __init__(self) -> None:
        self.held: dict[str, int] = {}

    @contextlib.contextmanager
    def charge(self, manager: str, max_message_size: int) -> Iterator[Callable[[int], None]]:
        """For one stream of ``manager``: a function told the stream's decoder's buffered
        bytes after each read, raising :class:`PolicyDenied` (``partial_frames``) when the
        peer's sum is over the limit. The stream's share is given back when it ends."""
        limit = PARTIAL_FRAMES_PER_PEER * max_message_size
        share = 0

        def update(buffered: int) -> None:
            nonlocal share
            held = self.held.get(manager, 0) - share + buffered
            self.held[manager], share = held, buffered
            if held > limit:
                raise PolicyDenied("partial_frames", (
                    f"{manager}'s unfinished frames would take {held} bytes here; the limit is "
                    f"{limit} ({PARTIAL_FRAMES_PER_PEER} x [ros2] max_message_size)"))

        try:
            yield update
        finally:
            left = self.held.get(manager, 0) - share
            if left > 0:
                self.held[manager] = left
            else:
                self.held.pop(manager, None)


__all__ = ["PARTIAL_FRAMES_PER_PEER", "PartialFrames"]
