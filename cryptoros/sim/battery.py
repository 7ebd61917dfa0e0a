"""Battery: time-based discharge plus the cost of moving, radio and crypto.

Figures default to a TurtleBot3 Burger: an 11.1 V 1800 mAh LiPo (about 72 kJ) that
lasts about 2.5 h in normal use. The model is deliberately simple (the paper's):
energy falls linearly with time at ``idle_w``, and every action adds its own cost.
No clock inside: callers pass the elapsed time, so any driver can run it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

BURGER_CAPACITY_J = 11.1 * 1.8 * 3600  # 71 928 J


@dataclass
class BatterySpec:
    capacity_j: float = BURGER_CAPACITY_J
    idle_w: float = 6.0  # computer + lidar + idle motors
    move_j_per_m: float = 14.0  # ~3 W of traction at 0.22 m/s
    tx_j_per_byte: float = 8e-6  # ~1 W radio at 1 Mbit/s
    rx_j_per_byte: float = 5e-6
    cpu_w: float = 2.5  # extra draw of a busy CPU (crypto)
    charge_w: float = 40.0  # charging station power


@dataclass
class Battery:
    spec: BatterySpec = field(default_factory=BatterySpec)
    energy: float = -1.0
    used: dict[str, float] = field(default_factory=lambda: {"idle": 0.0, "move": 0.0, "tx": 0.0, "rx": 0.0, "crypto": 0.0})

    def __post_init__(self) -> None:
        if self.energy < 0:
            self.energy = self.spec.capacity_j

    @property
    def fraction(self) -> float:
        return max(0.0, self.energy / self.spec.capacity_j)

    @property
    def empty(self) -> bool:
        return self.energy <= 0.0

    def _take(self, kind: str, joules: float) -> None:
        self.used[kind] += joules
        self.energy = max(0.0, self.energy - joules)

    def elapse(self, seconds: float) -> None:
        self._take("idle", self.spec.idle_w * seconds)

    def move(self, metres: float) -> None:
        self._take("move", self.spec.move_j_per_m * metres)

    def tx(self, nbytes: int) -> None:
        self._take("tx", self.spec.tx_j_per_byte * nbytes)

    def rx(self, nbytes: int) -> None:
        self._take("rx", self.spec.rx_j_per_byte * nbytes)

    def crypto(self, cpu_seconds: float) -> None:
        self._take("crypto", self.spec.cpu_w * cpu_seconds)

    def charge(self, seconds: float) -> None:
        self.energy = min(self.spec.capacity_j, self.energy + self.spec.charge_w * seconds)

    def time_to_full(self) -> float:
        return (self.spec.capacity_j - self.energy) / self.spec.charge_w

    def cost_to_travel(self, metres: float, speed: float) -> float:
        """Energy to drive ``metres`` at ``speed``: traction plus idle draw on the way."""
        return metres * self.spec.move_j_per_m + self.spec.idle_w * metres / speed

    def time_to_empty(self) -> float:
        """Seconds until empty if the robot only idles."""
        return self.energy / self.spec.idle_w
