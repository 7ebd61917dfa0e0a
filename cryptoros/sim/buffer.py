"""Frame buffer: camera frames stored in proportion to the distance travelled,
unloaded at a charging station."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class FrameBuffer:
    frames_per_m: float = 2.0
    capacity: int = 10_000
    frames: int = 0
    dropped: int = 0
    unloaded: int = 0
    _carry: float = 0.0

    def travelled(self, metres: float) -> None:
        self._carry += metres * self.frames_per_m
        new = int(self._carry)
        self._carry -= new
        room = self.capacity - self.frames
        self.frames += min(new, room)
        self.dropped += max(0, new - room)

    @property
    def free_share(self) -> float:
        """Free space as a share of the capacity (what HELLOs and LSUs advertise)."""
        return max(0.0, 1.0 - self.frames / self.capacity)

    @property
    def full(self) -> bool:
        return self.frames >= self.capacity

    def unload(self) -> int:
        n, self.frames = self.frames, 0
        self.unloaded += n
        return n
