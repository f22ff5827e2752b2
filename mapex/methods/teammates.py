"""What a robot of a team knows of its teammates when it decides, besides the shared map
and their claims (docs/algorithms.md#teams): every robot's pose after the previous step.

Every planner holds the same view at a step (the world sends every robot's pose with each
step's scans), so methods that compute something for the whole team from it (an assignment
of robots to frontiers, a partition of the map) compute the same thing in one process and
across processes. `cache` holds such computations for the robots decided in one process at
one step: a value there must depend only on the step's shared state (map, prediction,
poses), never on the robot that computed it first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mapex.grid import Cell


@dataclass(frozen=True)
class TeamView:
    """Robot `robot` deciding step `t`: every robot's cell after step t - 1 (None: lost)."""

    robot: int
    t: int
    poses: tuple[Cell | None, ...]
    cache: dict[object, Any] = field(default_factory=dict)

    @property
    def live(self) -> list[int]:
        """The robots still in the team (this one included), in robot order."""
        return [robot for robot, pose in enumerate(self.poses) if pose is not None]

    @property
    def alone(self) -> bool:
        """No teammate left: the robot decides as a single robot does."""
        return len(self.live) < 2

    def shared(self, key: object, compute: Callable[[], Any]) -> Any:
        """`compute()`, once per `key` for the robots decided in this process at this step."""
        if key not in self.cache:
            self.cache[key] = compute()
        return self.cache[key]
