"""MapEx and its ablations: information gain over a raycast visible set, per unit distance.

docs/algorithms.md#methods: the visible set of a frontier is every cell one of 250 rays (20 m)
traverses before it stops, minus cells already known. The methods differ in the
map the rays walk (what stops them) and in what each visible cell is worth.
"""

from __future__ import annotations

import numpy as np

from mapex.grid import OCCUPIED
from mapex.methods.base import FrontierScorer, PlanningContext
from mapex.visibility import group_visibility_gain, visibility_gain


def frontier_gain(
    context: PlanningContext,
    opacity: np.ndarray,
    weights: np.ndarray,
    stop_rule: str,
    epsilon: float,
) -> np.ndarray:
    """Sum of `weights` over each frontier's visible set, rays stopped by `opacity`."""
    cfg = context.config.visibility
    return visibility_gain(
        opacity.astype(np.float32, copy=False),
        weights,
        context.frontiers,
        cfg.n_rays,
        cfg.range_cells,
        stop_rule,
        epsilon,
    )


def known_walls(context: PlanningContext) -> np.ndarray:
    """float32 opacity with only the observed walls opaque (unknown cells let rays through)."""
    return (context.observed == OCCUPIED).astype(np.float32)


def path_group_gain(
    context: PlanningContext,
    opacity: np.ndarray,
    weights: np.ndarray,
    groups: list[np.ndarray],
    stop_rule: str,
    epsilon: float,
) -> np.ndarray:
    """Sum of `weights` over the union of the visible sets of each group of viewpoints (the
    samples of a path), rays stopped by `opacity`."""
    cfg = context.config.visibility
    return group_visibility_gain(
        opacity.astype(np.float32, copy=False),
        weights,
        groups,
        cfg.n_rays,
        cfg.range_cells,
        stop_rule,
        epsilon,
    )


def _predicted_walls_gain(context: PlanningContext, weights: np.ndarray) -> np.ndarray:
    """Gain with deterministic rays on the thresholded main prediction P_t (p >= 0.5 blocks)."""
    cfg = context.config.visibility
    return frontier_gain(
        context, context.prediction.main, weights, "threshold", cfg.occupied_threshold
    )


def mapex_gain(context: PlanningContext) -> np.ndarray:
    """MapEx's gain: the sum of V_t over each frontier's probabilistically visible set
    (rays on M_t, the configured stop rule)."""
    cfg = context.config.visibility
    weights = context.unknown_weights(context.prediction.variance)
    return frontier_gain(context, context.prediction.mean, weights, cfg.stop_rule, cfg.epsilon)


class MapEx(FrontierScorer):
    """MapEx: sum of V_t over the probabilistically visible set (rays on M_t) / distance."""

    name = "mapex"
    uses_prediction = True
    reads_main = False  # V_t and M_t of G_1..G_n only

    def score(self, context: PlanningContext) -> np.ndarray:
        return mapex_gain(context) / context.frontier_distances()


class Deterministic(FrontierScorer):
    """Ablation: sum of V_t over the set visible in thresholded P_t / distance."""

    name = "deterministic"
    uses_prediction = True

    def score(self, context: PlanningContext) -> np.ndarray:
        weights = context.unknown_weights(context.prediction.variance)
        return _predicted_walls_gain(context, weights) / context.frontier_distances()


class NoVariance(FrontierScorer):
    """Ablation: number of unknown cells visible in thresholded P_t / distance."""

    name = "no_variance"
    uses_prediction = True
    reads_members = False  # P_t of G only

    def score(self, context: PlanningContext) -> np.ndarray:
        weights = context.unknown_weights(1.0)
        return _predicted_walls_gain(context, weights) / context.frontier_distances()


class ObservedMap(FrontierScorer):
    """Ablation: number of unknown cells visible when only known walls block / distance."""

    name = "observed_map"

    def score(self, context: PlanningContext) -> np.ndarray:
        weights = context.unknown_weights(1.0)
        gain = frontier_gain(context, known_walls(context), weights, "threshold", 1.0)
        return gain / context.frontier_distances()


class NoVisibility(FrontierScorer):
    """Ablation: sum of V_t within 5 m of the frontier (no raycast) / distance."""

    name = "no_visibility"
    uses_prediction = True
    reads_main = False  # V_t and M_t of G_1..G_n only

    def score(self, context: PlanningContext) -> np.ndarray:
        variance = context.unknown_weights(context.prediction.variance)
        radius = context.config.visibility.no_visibility_radius_cells
        gains = np.array([_disc_sum(variance, f, radius) for f in context.frontiers])
        return gains / context.frontier_distances()


def _disc_sum(values: np.ndarray, centre: np.ndarray, radius_cells: int) -> float:
    """Sum of `values` over the disc of `radius_cells` around `centre` (clipped to the map)."""
    row, col = int(centre[0]), int(centre[1])
    r0, c0 = max(row - radius_cells, 0), max(col - radius_cells, 0)
    window = values[r0 : row + radius_cells + 1, c0 : col + radius_cells + 1]
    rows, cols = np.ogrid[r0 : r0 + window.shape[0], c0 : c0 + window.shape[1]]
    inside = (rows - row) ** 2 + (cols - col) ** 2 <= radius_cells**2
    return float(window[inside].sum(dtype=np.float64))
