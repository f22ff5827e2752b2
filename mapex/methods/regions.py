"""`mapex_voronoi`: each robot explores its own part of the predicted building, the cells
nearer to it than to any teammate by path (docs/algorithms.md#teams).

The robots' poses split the map into Voronoi cells of path distance: a Dijkstra from every
robot over the known free cells and the unknown cells the ensemble predicts free (mean
occupancy M_t below `team.region_wall_probability`); each cell goes to the nearest robot
(ties: the lower robot). A robot scores only the frontiers in its own cell (the others are
tried last), by MapEx's gain counting only the unknown cells that are not in a teammate's
cell, per distance. A robot whose cell holds no frontier waits (teammates have the work)
and looks again after `team.idle_replan_steps`: as they drive away, the cells near it
become its own. Every robot computes the same cells from the shared map, prediction and
poses (`mapex.methods.teammates`); nothing is claimed. Alone it is `mapex`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numba import njit

from mapex.config import ExplorationConfig
from mapex.grid import FREE, UNKNOWN, Cell
from mapex.methods.base import PlanningContext
from mapex.methods.goals import Goal
from mapex.methods.information_gain import MapEx
from mapex.prediction.base import EnsemblePrediction
from mapex.search import _HEAP_START_CAPACITY, _heap_pop, _heap_push, _heap_room, _move_tables


def region_cost(
    observed: np.ndarray, prediction: EnsemblePrediction | None, wall_probability: float
) -> np.ndarray:
    """float32 cost map of the partition: 1 on known free cells and on unknown cells
    predicted free (M_t below `wall_probability`: cells outside the predicted region hold
    0.5, as unknown, and are out; all unknown cells without a prediction), inf elsewhere."""
    passable = observed == FREE
    unknown = observed == UNKNOWN
    if prediction is None:
        passable |= unknown
    else:
        passable |= unknown & (prediction.mean < wall_probability)
    return np.where(passable, np.float32(1.0), np.float32(np.inf)).astype(np.float32)


def path_voronoi(cost: np.ndarray, poses: Sequence[Cell]) -> np.ndarray:
    """int64 (rows, cols): the index in `poses` of the robot nearest to each cell by path
    on `cost` (moves as `mapex.search`'s; ties: the lower index), -1 where no robot can get.
    One Dijkstra from all the robots at once; a robot's own cell is passable."""
    rows, cols = cost.shape
    width = cols + 2
    padded = np.full((rows + 2) * width, np.inf, dtype=np.float32)
    padded.reshape(rows + 2, width)[1:-1, 1:-1] = cost
    sources = np.array([(r + 1) * width + c + 1 for r, c in poses], dtype=np.int64)
    padded[sources] = np.where(np.isfinite(padded[sources]), padded[sources], 1.0)
    labels = _nearest_source(padded, padded < np.inf, width, sources)
    return labels.reshape(rows + 2, width)[1:-1, 1:-1].copy()


@njit(cache=True)
def _nearest_source(padded, passable, width, sources):
    """Multi-source Dijkstra on the padded flat map: the index of each cell's nearest
    source (heap order: distance, then source index, then cell), -1 where none gets."""
    target, via_row, via_col, length = _move_tables(width)
    g = np.full(padded.size, np.inf)
    label = np.full(padded.size, -1, dtype=np.int64)
    closed = np.zeros(padded.size, dtype=np.bool_)
    capacity = max(_HEAP_START_CAPACITY, 2 * sources.size)
    keys = np.empty(capacity)
    ties = np.empty(capacity)
    nodes = np.empty(capacity, dtype=np.int64)
    size = 0
    for s in range(sources.size):
        node = sources[s]
        if label[node] < 0:
            g[node] = 0.0
            label[node] = s
            size = _heap_push(keys, ties, nodes, size, 0.0, float(s), node)
    while size > 0:
        node, size = _heap_pop(keys, ties, nodes, size)
        if closed[node]:
            continue
        closed[node] = True
        keys, ties, nodes = _heap_room(keys, ties, nodes, size)
        for k in range(8):
            nxt = node + target[k]
            if closed[nxt] or not passable[nxt]:
                continue
            if not (passable[node + via_row[k]] and passable[node + via_col[k]]):
                continue
            candidate = g[node] + padded[nxt] * length[k]
            if candidate < g[nxt] or (candidate == g[nxt] and label[node] < label[nxt]):
                g[nxt] = candidate
                label[nxt] = label[node]
                size = _heap_push(keys, ties, nodes, size, candidate, float(label[node]), nxt)
    return label


class MapExVoronoi(MapEx):
    """MapEx within the robot's own path-distance Voronoi cell (module doc)."""

    name = "mapex_voronoi"
    made_for_teams = True

    def __init__(self, config: ExplorationConfig) -> None:
        super().__init__(config)
        self._mine: np.ndarray | None = None  # bool (K,): the frontiers in the robot's cell

    def select_goal(self, context: PlanningContext) -> Goal | None:
        self.waiting, self._mine = False, None
        view = self.team_view
        if view is None or view.alone or len(context.frontiers) == 0:
            return super().select_goal(context)
        live = view.live
        poses = [view.poses[robot] for robot in live]
        wall = self.config.team.region_wall_probability
        labels = view.shared(
            ("path_voronoi", tuple(poses)),
            lambda: path_voronoi(region_cost(context.observed, context.prediction, wall), poses),
        )
        me = live.index(view.robot)
        at = labels[context.frontiers[:, 0], context.frontiers[:, 1]]
        mine = (at == me) | (at < 0)  # a frontier no robot can get to is everybody's
        if not mine.any():
            self.waiting, self.last_scores = True, None
            return None
        theirs = (labels >= 0) & (labels != me)
        claimed = theirs if context.claimed is None else context.claimed | theirs
        self._mine = mine
        try:
            return super().select_goal(replace(context, claimed=claimed))
        finally:
            self._mine = None

    def score(self, context: PlanningContext) -> np.ndarray:
        scores = super().score(context)
        if self._mine is None:
            return scores
        return np.where(self._mine, scores, -np.inf)
