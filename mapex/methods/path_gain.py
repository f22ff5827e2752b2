"""Beyond the paper: MapEx with real path costs and the gain along the way
(docs/algorithms.md#beyond-the-paper).

* `mapex_path`: MapEx's gain divided by the wall-aware path cost from the robot
  (`mapex.methods.paths`) instead of the straight-line distance.
* `mapex_plus`: the worth of every cell visible (rays on M_t) from samples of the path to a
  frontier and from the frontier itself, mixing expected new area with V_t, per path cost
  plus a fixed trip cost, re-planned periodically; only the `path_gain.top_k` frontiers
  with the best frontier-only score (a lower bound) are raycast along their paths.
"""

from __future__ import annotations

import numpy as np

from mapex.config import ExplorationConfig
from mapex.grid import UNKNOWN
from mapex.methods.base import FrontierScorer, PlanningContext
from mapex.methods.information_gain import frontier_gain, mapex_gain, path_group_gain
from mapex.methods.paths import FrontierPaths, frontier_paths


def per_path_cost(gain: np.ndarray, path_cost: np.ndarray, offset_cells: float = 0.0) -> np.ndarray:
    """gain / (path cost + offset) (at least 1 cell); -inf for unreachable frontiers."""
    finite = np.isfinite(path_cost)
    return np.where(finite, gain / np.maximum(path_cost + offset_cells, 1.0), -np.inf)


def revealed_cell_worth(context: PlanningContext, variance_weight: float) -> np.ndarray:
    """float32 map: (1 - w) + w x V_t / mean V_t on unknown cells, 0 on known ones.

    The variance is scaled by its mean over the unknown cells where it is positive, so both
    terms are worth 1 per cell on average whatever the ensemble's spread. With no variance
    anywhere (e.g. a single member answered) every unknown cell is worth 1: area only.
    """
    variance = context.prediction.variance
    disputed = (context.observed == UNKNOWN) & (variance > 0)
    if not disputed.any():
        return context.unknown_weights(1.0)
    relative = variance / np.float32(variance[disputed].mean(dtype=np.float64))
    return context.unknown_weights((1.0 - variance_weight) + variance_weight * relative)


def path_viewpoints(path: np.ndarray, frontier: np.ndarray, every_cells: int) -> np.ndarray:
    """int64 (n, 2): every `every_cells`-th cell of `path` after the robot's own, then the
    frontier point (the robot has already scanned from where it stands)."""
    samples = np.asarray(path, dtype=np.int64)[every_cells::every_cells]
    return np.vstack([samples, np.asarray(frontier, dtype=np.int64)[None]])


class MapExPath(FrontierScorer):
    """MapEx's gain per unit of wall-aware path cost (one Dijkstra per re-plan)."""

    name = "mapex_path"
    uses_prediction = True
    reads_main = False  # V_t and M_t of G_1..G_n only

    def score(self, context: PlanningContext) -> np.ndarray:
        return per_path_cost(mapex_gain(context), frontier_paths(context).cost)


class MapExPlus(FrontierScorer):
    """Worth of the cells seen along the path and at the frontier, per unit path cost."""

    name = "mapex_plus"
    uses_prediction = True
    reads_main = False  # V_t and M_t of G_1..G_n only

    def __init__(self, config: ExplorationConfig) -> None:
        super().__init__(config)
        self.replan_every_steps = config.path_gain.replan_every_steps or None

    def worth(self, context: PlanningContext) -> np.ndarray:
        """float32 map: what each cell seen is worth (0 on known cells)."""
        return revealed_cell_worth(context, context.config.path_gain.variance_weight)

    def opacity(self, context: PlanningContext) -> tuple[np.ndarray, str, float]:
        """The map the rays walk, with its stop rule and level: M_t, as MapEx."""
        visibility = context.config.visibility
        return context.prediction.mean, visibility.stop_rule, visibility.epsilon

    def score(self, context: PlanningContext) -> np.ndarray:
        settings = context.config.path_gain
        worth = self.worth(context)
        opacity, stop_rule, epsilon = self.opacity(context)
        at_frontier = frontier_gain(context, opacity, worth, stop_rule, epsilon)
        paths = frontier_paths(context)
        offset = settings.cost_offset_cells
        cost = paths.cost if settings.cost_measure == "planner" else path_cells(paths)
        scores = per_path_cost(at_frontier, cost, offset)
        ranked = [i for i in np.argsort(-scores, kind="stable") if np.isfinite(scores[i])]
        candidates = np.array(ranked[: settings.top_k], dtype=np.int64)
        groups = [
            path_viewpoints(paths.path(i), context.frontiers[i], settings.path_sample_cells)
            for i in candidates
        ]
        along = path_group_gain(context, opacity, worth, groups, stop_rule, epsilon)
        scores[candidates] = per_path_cost(along, cost[candidates], offset)
        return scores


def path_cells(paths: FrontierPaths) -> np.ndarray:
    """float64 (K,): the number of moves of each frontier's path (inf where unreachable)."""
    return np.array(
        [
            np.inf if not np.isfinite(c) else len(paths.path(i)) - 1
            for i, c in enumerate(paths.cost)
        ],
        dtype=np.float64,
    )
