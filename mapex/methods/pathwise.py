"""The authors' pathwise follow-up, PIPE (Baek et al., IROS 2025), and its no-prediction twin
(docs/algorithms.md#pipe).

* `pipe`: for each reachable frontier, the cells seen from every 3rd cell of the path to it
  (250 rays, 20 m, stopped on the ensemble mean M_t at 0.8), each counted once; score = the
  sum of the ensemble variance V_t over the unknown ones / the number of path samples.
* `pw_nbv` (their `pw-nbv-2d`): the same union, rays stopped by known walls only; score =
  the number of unknown cells in it / the number of path samples.
* `mapex_plus_observed`: `mapex_plus`'s own twin without prediction (its path samples, trip
  cost and re-planning, rays on known walls, every unknown cell worth 1).
"""

from __future__ import annotations

import numpy as np

from mapex.methods.base import FrontierScorer, PlanningContext
from mapex.methods.information_gain import known_walls, path_group_gain
from mapex.methods.path_gain import MapExPlus
from mapex.methods.paths import frontier_paths


def pipe_samples(path: np.ndarray, every_cells: int) -> np.ndarray:
    """int64 (n, 2): the authors' `path[n-1::n]` (every n-th cell, the robot's own cell
    excluded); a path too short to have one is represented by its last cell."""
    path = np.asarray(path, dtype=np.int64).reshape(-1, 2)
    samples = path[every_cells - 1 :: every_cells]
    return samples if len(samples) else path[-1:]


def pathwise_scores(
    context: PlanningContext, opacity: np.ndarray, worth: np.ndarray, stop_rule: str, epsilon: float
) -> np.ndarray:
    """float64 (K,): the worth of the union of the cells visible from each frontier's path
    samples / the number of samples; -inf for frontiers no path reaches."""
    paths = frontier_paths(context)
    scores = np.full(len(context.frontiers), -np.inf)
    reachable = np.flatnonzero(np.isfinite(paths.cost))
    every = context.config.pipe.path_sample_cells
    groups = [pipe_samples(paths.path(int(i)), every) for i in reachable]
    gains = path_group_gain(context, opacity, worth, groups, stop_rule, epsilon)
    scores[reachable] = gains / np.array([max(len(group), 1) for group in groups], dtype=float)
    return scores


class Pipe(FrontierScorer):
    """PIPE: ensemble variance over the set seen along the path / path samples."""

    name = "pipe"
    uses_prediction = True
    reads_main = False  # V_t and M_t of G_1..G_n only

    def score(self, context: PlanningContext) -> np.ndarray:
        visibility = context.config.visibility
        worth = context.unknown_weights(context.prediction.variance)
        return pathwise_scores(
            context, context.prediction.mean, worth, visibility.stop_rule, visibility.epsilon
        )


class PathwiseNbv(FrontierScorer):
    """PIPE's no-prediction baseline: unknown cells seen along the path / path samples."""

    name = "pw_nbv"

    def score(self, context: PlanningContext) -> np.ndarray:
        worth = context.unknown_weights(1.0)
        return pathwise_scores(context, known_walls(context), worth, "threshold", 1.0)


class MapExPlusObserved(MapExPlus):
    """`mapex_plus` without prediction: its path terms with rays on the observed map."""

    name = "mapex_plus_observed"
    uses_prediction = False
    reads_main = False
    reads_members = False

    def worth(self, context: PlanningContext) -> np.ndarray:
        return context.unknown_weights(1.0)

    def opacity(self, context: PlanningContext) -> tuple[np.ndarray, str, float]:
        return known_walls(context), "threshold", 1.0
