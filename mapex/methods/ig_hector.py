"""IG-Hector baseline (Shrestha et al. 2019): predicted-map information gain on the
Hector exploration transform.

The gain of a frontier is the number of unknown cells visible in the thresholded
prediction P_t. Its cost is the exploration transform: the wall-penalised path
cost from the robot (the planning cost map's Dijkstra distance). The frontier
with the highest `gain - path_cost_weight * cost` wins.
"""

from __future__ import annotations

import numpy as np

from mapex.methods.base import FrontierScorer, PlanningContext
from mapex.methods.information_gain import frontier_gain
from mapex.search import shortest_path_tree


class IgHector(FrontierScorer):
    """Utility = visible unknown cells in thresholded P_t - weight x exploration-transform cost."""

    name = "ig_hector"
    uses_prediction = True

    def score(self, context: PlanningContext) -> np.ndarray:
        cfg = context.config.visibility
        weights = context.unknown_weights(1.0)
        gain = frontier_gain(
            context, context.prediction.main, weights, "threshold", cfg.occupied_threshold
        )
        path_cost = exploration_transform_cost(context)
        return gain - self.config.ig_hector.path_cost_weight * path_cost


def exploration_transform_cost(context: PlanningContext) -> np.ndarray:
    """Wall-penalised path cost from the robot to each frontier (inf where unreachable)."""
    distance, _ = shortest_path_tree(context.cost, (int(context.pose[0]), int(context.pose[1])))
    rows, cols = context.frontiers[:, 0], context.frontiers[:, 1]
    direct = distance[rows, cols].astype(np.float64)
    # A frontier next to a wall may itself be inflated: reach it from its cheapest neighbour.
    padded = np.pad(distance, 1, constant_values=np.inf)
    neighbours = np.stack(
        [padded[rows + 1 + dr, cols + 1 + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
    )
    return np.minimum(direct, neighbours.min(axis=0) + 1.0)
