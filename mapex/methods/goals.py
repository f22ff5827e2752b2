"""Where the robot drives to explore a frontier cluster: the cluster's goal
(docs/algorithms.md#goals).

The robot only drives through known-free cells with a cell of clearance, so a cluster's
frontier point may be out of reach: a door seen at a grazing angle shows only a one-cell
diagonal sliver of free cells, which no path without corner cutting can follow. The goal
of a cluster is therefore, in this order:

1. its frontier point, when reachable;
2. else the reachable frontier cell of the cluster nearest (Euclidean) to the point;
3. else, when no cell of the cluster is reachable, the reachable known-free cell nearest
   to the cluster, the one nearest to the point among equally near ones (the robot
   approaches and keeps scanning, which reveals the space behind the sliver).

A cell the robot has already scanned from is never a goal: the world is static and the
LiDAR noise-free, so a second scan from there reveals nothing new. A cluster whose rule
lands on such a cell is exhausted for now: the robot stood at its approach cell and the
scan from there changed nothing (a later scan elsewhere may change the cluster, and with it
its goal). Ties go to the earliest cell in row-major order. Scores are always those of the
frontier point.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from mapex.grid import FREE

if TYPE_CHECKING:
    from mapex.methods.base import PlanningContext


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


def cluster_goal(context: PlanningContext, index: int) -> Goal | None:
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
    context: PlanningContext, members: np.ndarray, point: np.ndarray
) -> np.ndarray | None:
    """The reachable member nearest to `point` (the point itself when reachable), or None."""
    offsets = members - point
    order = np.argsort(np.einsum("ij,ij->i", offsets, offsets), kind="stable")
    for cell in members[order]:
        if context.can_reach(cell):
            return cell.astype(np.int64)
    return None


def _approach_cell(
    context: PlanningContext, members: np.ndarray, point: np.ndarray
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
