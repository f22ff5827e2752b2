"""The world side of an episode: ground truth, robot poses, motion checks and LiDAR scans.

This is what the `services.world` process wraps; in one process the episode
loop calls it directly. It answers a *step* (the cells the robot drives
through this timestep) with the scan taken at the new pose.
"""

from __future__ import annotations

import numpy as np

from mapex.config import MotionConfig, SensorConfig
from mapex.grid import Cell
from mapex.sensor import Scan, cast_scan
from mapex.worlds.base import World


class MotionError(ValueError):
    """A requested motion that is not a chain of 8-connected moves through free cells."""


class Simulator:
    """Holds the ground truth and the pose of each robot; moves robots and scans."""

    def __init__(
        self, world: World, starts: list[Cell], sensor: SensorConfig, motion: MotionConfig
    ) -> None:
        self.world = world
        self.sensor = sensor
        self.motion = motion
        self.poses = [np.array(start, dtype=np.int64) for start in starts]
        for start in starts:
            self._check_free(start)

    def scan(self, robot: int) -> Scan:
        """The LiDAR scan at robot `robot`'s current pose (the initial scan before t = 0)."""
        pose = self.poses[robot]
        return cast_scan(self.world.occupancy, (int(pose[0]), int(pose[1])), self.sensor)

    def step(self, robot: int, cells: np.ndarray) -> Scan:
        """Drive robot `robot` through `cells` (k <= cells_per_step, each one 8-connected move)
        and return the scan at its new pose."""
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        limit = self.motion.cells_per_step
        if len(cells) > limit:
            raise MotionError(f"robot {robot}: {len(cells)} cells in one step (at most {limit})")
        previous = self.poses[robot]
        for cell in cells:
            if np.abs(cell - previous).max() != 1:
                raise MotionError(
                    f"robot {robot}: {tuple(previous)} -> {tuple(cell)} is not one move"
                )
            self._check_free(cell)
            previous = cell
        self.poses[robot] = previous.copy()
        return self.scan(robot)

    def _check_free(self, cell) -> None:
        rows, cols = self.world.shape
        row, col = int(cell[0]), int(cell[1])
        if not (0 <= row < rows and 0 <= col < cols) or self.world.occupancy[row, col]:
            raise MotionError(f"cell {(row, col)} is outside the map or a wall")
