"""Where the robot drives to explore a frontier cluster: the cluster's goal
(docs/algorithms.md#goals).

The robot only drives through known-free cells with a cell of clearance, so a cluster's
frontier point may be out of reach (a door seen at a grazing angle shows only a one-cell
diagonal sliver of free cells). The goal is the frontier point when reachable, else the
nearest reachable frontier cell of the cluster, else the nearest reachable known-free cell;
never a cell the robot has already scanned from. Ties go to the earliest cell in row-major
order. Scores are always those of the frontier point.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from mapex.grid import FREE


class GoalContext(Protocol):
    """What the goal rule reads of `mapex.methods.base.PlanningContext` (described here, not
    imported: that module imports this one)."""

    @property
    def observed(self) -> np.ndarray: ...
    @property
    def frontiers(self) -> np.ndarray: ...
    @property
    def reachable(self) -> np.ndarray: ...
    def can_reach(self, cell: np.ndarray) -> bool: ...
    def cluster_members(self, index: int) -> np.ndarray: ...
    def was_scanned_from(self, cell: np.ndarray) -> bool: ...


@dataclass(frozen=True)
class Goal:
    """A goal the planner drives to.

    cell: int64 (2,) known-free reachable cell to drive to; frontier: the frontier point the
    goal serves (None for a goal of the method's own, such as UPEN's). An *approach* goal
    (cell is not the frontier point) is reached only by standing on it, and is kept while
    unknown cells remain near its frontier point.
    """

    cell: np.ndarray
    frontier: np.ndarray | None = None

    @property
    def approach(self) -> bool:
        return self.frontier is not None and not np.array_equal(self.cell, self.frontier)


def cluster_goal(context: GoalContext, index: int) -> Goal | None:
    """The goal of frontier cluster `index` by the rule above, or None when it has none."""
    point = np.asarray(context.frontiers[index], dtype=np.int64)
    members = context.cluster_members(index)
    cell = _nearest_reachable_member(context, members, point)
    if cell is None:
        cell = _approach_cell(context, members, point)
    if cell is None or context.was_scanned_from(cell):
        return None
    return Goal(cell, point)


def _nearest_reachable_member(
    context: GoalContext, members: np.ndarray, point: np.ndarray
) -> np.ndarray | None:
    """The reachable member nearest to `point` (the point itself when reachable), or None."""
    offsets = members - point
    order = np.argsort(np.einsum("ij,ij->i", offsets, offsets), kind="stable")
    for cell in members[order]:
        if context.can_reach(cell):
            return cell.astype(np.int64)
    return None


def _approach_cell(
    context: GoalContext, members: np.ndarray, point: np.ndarray
) -> np.ndarray | None:
    """The reachable known-free cell nearest (Euclidean) to any member; of those equally near,
    the one nearest to the frontier point (then row-major first). None when there is none."""
    standing = context.reachable & (context.observed == FREE)
    if not standing.any():
        return None
    not_member = np.ones(context.observed.shape, dtype=np.uint8)
    not_member[members[:, 0], members[:, 1]] = 0
    distance = cv2.distanceTransform(not_member, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    distance = np.where(standing, distance, np.inf)
    nearest = np.argwhere(distance == distance.min())
    offsets = nearest - point
    return nearest[int(np.argmin(np.einsum("ij,ij->i", offsets, offsets)))].astype(np.int64)
