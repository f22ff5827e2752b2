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
from mapex.methods.paths import frontier_paths


class IgHector(FrontierScorer):
    """Utility = visible unknown cells in thresholded P_t - weight x exploration-transform cost."""

    name = "ig_hector"
    uses_prediction = True
    reads_members = False  # P_t of G only

    def score(self, context: PlanningContext) -> np.ndarray:
        cfg = context.config.visibility
        weights = context.unknown_weights(1.0)
        gain = frontier_gain(
            context, context.prediction.main, weights, "threshold", cfg.occupied_threshold
        )
        path_cost = frontier_paths(context).cost
        return gain - self.config.ig_hector.path_cost_weight * path_cost
