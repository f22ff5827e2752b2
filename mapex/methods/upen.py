"""UPEN baseline (Georgakis et al. 2022): go where the ensemble disagrees most along a path.

An RRT is grown from the robot over cells the mean prediction calls free; the
tree path with the largest sum of V_t along it wins and the robot heads for its
end. Since the robot may only drive through known-free space, the goal is the
reachable known-free cell nearest to that end; the planner re-plans every
`replan_every_steps` steps. When that cell is one the robot has already scanned from, the
nearest frontier's goal is taken instead (a second scan there would show nothing new).
"""

from __future__ import annotations

import numpy as np

from mapex.grid import FREE, UNKNOWN
from mapex.methods.base import Method, PlanningContext
from mapex.methods.goals import Goal
from mapex.methods.nearest import NearestFrontier


class Upen(Method):
    """Uncertainty-driven RRT path selection."""

    name = "upen"
    uses_prediction = True
    reads_main = False  # V_t and M_t of G_1..G_n only
    drop_goal_without_unknown = False

    def __init__(self, config) -> None:
        super().__init__(config)
        self.replan_every_steps = config.upen.replan_every_steps
        self._fallback = NearestFrontier(config)

    def select_goal(self, context: PlanningContext) -> Goal | None:
        if len(context.frontiers) == 0:
            return None
        end = best_rrt_endpoint(context)
        goal = nearest_reachable_cell(context, end)
        if goal is None or context.was_scanned_from(goal):  # a second scan there shows nothing
            return self._fallback.select_goal(context)
        return Goal(goal)


def predicted_free(context: PlanningContext) -> np.ndarray:
    """Cells UPEN may plan through: known free, or unknown with mean occupancy below 0.5."""
    threshold = context.config.visibility.occupied_threshold
    unknown_free = (context.observed == UNKNOWN) & (context.prediction.mean < threshold)
    return (context.observed == FREE) | unknown_free


def best_rrt_endpoint(context: PlanningContext) -> np.ndarray:
    """End cell of the RRT path with the largest variance sum."""
    cfg = context.config.upen
    free = predicted_free(context)
    variance = context.unknown_weights(context.prediction.variance)
    nodes = [context.pose.astype(np.float64) + 0.5]
    values = [0.0]
    shape = np.array(free.shape, dtype=np.float64)
    for _ in range(cfg.rrt_iterations):
        sample = context.rng.random(2) * shape
        offsets = np.asarray(nodes) - sample
        parent = int(np.argmin(np.einsum("ij,ij->i", offsets, offsets)))
        new = _steer(nodes[parent], sample, cfg.rrt_step_cells)
        cells = _segment_cells(nodes[parent], new)
        if not free[cells[:, 0], cells[:, 1]].all():
            continue
        nodes.append(new)
        values.append(values[parent] + float(variance[cells[1:, 0], cells[1:, 1]].sum()))
    best = nodes[int(np.argmax(values))]
    return np.floor(best).astype(np.int64)


def nearest_reachable_cell(context: PlanningContext, target: np.ndarray) -> np.ndarray | None:
    """The reachable known-free cell closest (Euclidean) to `target`, or None."""
    candidates = np.argwhere(context.reachable & (context.observed == FREE))
    if len(candidates) == 0:
        return None
    offsets = candidates - target
    return candidates[int(np.argmin(np.einsum("ij,ij->i", offsets, offsets)))]


def _steer(start: np.ndarray, towards: np.ndarray, step_cells: float) -> np.ndarray:
    delta = towards - start
    length = float(np.hypot(*delta))
    return towards if length <= step_cells else start + delta * (step_cells / length)


def _segment_cells(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Cells under the straight segment, sampled every half cell (start first)."""
    n = max(int(np.ceil(np.hypot(*(end - start)) * 2)), 1)
    points = start + np.linspace(0.0, 1.0, n + 1)[:, None] * (end - start)
    return np.floor(points).astype(np.int64)
