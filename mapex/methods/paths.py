"""Paths from the robot to every frontier: one Dijkstra per re-plan over the planning cost map.

The cost of a path is the planner's own: the sum of the entered cells' costs (1 per cell in
the open, more near walls, docs/algorithms.md#navigation), x sqrt(2) per diagonal move. A
frontier point inside the wall inflation is entered from its cheapest neighbour (+1), as
A* would. Methods that pay the true path cost (IG-Hector's exploration transform,
`mapex_path`, `mapex_plus`) share this one computation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapex.methods.base import PlanningContext
from mapex.search import path_from_tree, shortest_path_tree

_NEIGHBOURS = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)], dtype=np.int64)


@dataclass(frozen=True)
class FrontierPaths:
    """cost: float64 (K,) path cost in cells to each frontier (inf where unreachable);
    entry: int64 (K, 2) the cell each path reaches (the point or its cheapest neighbour);
    start: the robot's cell; parent: the Dijkstra tree (`mapex.search.shortest_path_tree`)."""

    cost: np.ndarray
    entry: np.ndarray
    start: tuple[int, int]
    parent: np.ndarray

    def path(self, index: int) -> np.ndarray | None:
        """int32 (N, 2) cells from the robot to frontier `index`'s entry (None: unreachable)."""
        if not np.isfinite(self.cost[index]):
            return None
        return path_from_tree(self.parent, self.entry[index], self.start)


def frontier_paths(context: PlanningContext) -> FrontierPaths:
    """Cheapest paths from the robot to every frontier point of `context`."""
    start = (int(context.pose[0]), int(context.pose[1]))
    distance, parent = shortest_path_tree(context.cost, start)
    rows, cols = context.frontiers[:, 0].astype(np.int64), context.frontiers[:, 1].astype(np.int64)
    padded = np.pad(distance, 1, constant_values=np.inf)  # float32, as the tree
    # (9, K): the cost at each point's 3 x 3 neighbourhood, +1 to step onto the point
    around = np.stack([padded[rows + 1 + dr, cols + 1 + dc] for dr, dc in _NEIGHBOURS])
    direct = around[4].astype(np.float64)
    best = np.argmin(around, axis=0)
    via_neighbour = (around[best, np.arange(len(rows))] + np.float32(1.0)).astype(np.float64)
    use_point = direct <= via_neighbour
    cost = np.where(use_point, direct, via_neighbour)
    entry = np.stack([rows, cols], axis=1) + np.where(use_point[:, None], 0, _NEIGHBOURS[best])
    return FrontierPaths(cost, entry, start, parent)
