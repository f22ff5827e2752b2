"""Nearest-Frontier (Yamauchi 1997): go to the closest frontier."""

from __future__ import annotations

import numpy as np

from mapex.methods.base import FrontierScorer, PlanningContext


class NearestFrontier(FrontierScorer):
    """Score = minus the Euclidean distance from the robot (closest first)."""

    name = "nearest"

    def score(self, context: PlanningContext) -> np.ndarray:
        return -context.frontier_distances()
