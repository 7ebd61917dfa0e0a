"""Home handler: when to go back to a charging station, which one, and charging.

The decision is a pure function of position, battery and figures: a robot turns home
as soon as the energy to reach the nearest station (with a safety factor for detours
and a fixed reserve) would exceed what is left after one more step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from cryptoros.sim.battery import Battery


@dataclass
class HomeHandler:
    bases: list[tuple[int, int]]  # (row, col)
    resolution: float
    speed: float
    detour: float = 1.6  # path length / straight-line distance allowance
    reserve_j: float = 200.0

    def nearest(self, cell: tuple[int, int]) -> tuple[tuple[int, int], float]:
        """Nearest base and its straight-line distance in metres."""
        best, dist = self.bases[0], math.inf
        for b in self.bases:
            d = math.hypot(b[0] - cell[0], b[1] - cell[1]) * self.resolution
            if d < dist:
                best, dist = b, d
        return best, dist

    def energy_home(self, battery: Battery, cell: tuple[int, int]) -> float:
        _, d = self.nearest(cell)
        return battery.cost_to_travel(d * self.detour, self.speed) + self.reserve_j

    def must_return(self, battery: Battery, cell: tuple[int, int], step_m: float) -> bool:
        margin = battery.cost_to_travel(step_m * 2, self.speed)
        return battery.energy - margin <= self.energy_home(battery, cell)

    def can_reach(self, battery: Battery, cell: tuple[int, int], target: tuple[int, int]) -> bool:
        """Enough energy to drive to ``target`` and from there to the nearest base."""
        there = math.hypot(target[0] - cell[0], target[1] - cell[1]) * self.resolution * self.detour
        need = battery.cost_to_travel(there, self.speed) + self.energy_home(battery, target)
        return battery.energy > need

    def at_base(self, cell: tuple[int, int]) -> bool:
        return any(abs(b[0] - cell[0]) <= 1 and abs(b[1] - cell[1]) <= 1 for b in self.bases)
