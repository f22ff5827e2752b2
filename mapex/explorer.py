"""The robot brain: mapping, goal keeping and re-planning with one method
(docs/algorithms.md#navigation).

The explorer owns the observed map O_t. Each timestep it keeps its goal while the goal is
still worth going to (docs/algorithms.md#goals), otherwise it re-plans: predicts the map
(methods that use prediction), extracts frontiers, lets the method pick a goal and plans an
A* path to it. It then hands back the cells to drive through this step. It knows nothing of
processes: `services.planner` wraps it. A re-plan with fewer members than asked is
*degraded* and listed in the stats (docs/design.md#in-process-equals-distributed)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from mapex.config import ExplorationConfig
from mapex.frontiers import frontier_clusters
from mapex.grid import Cell, new_observed_map
from mapex.methods.base import Method, PlanningContext
from mapex.methods.goals import Goal
from mapex.methods.information_gain import ObservedMap
from mapex.navigation import (
    advance_along_path,
    cost_map,
    path_is_clear,
    plan_path,
    reachable_mask,
    unknown_within,
)
from mapex.prediction.base import EnsemblePrediction, Predictor, known_region
from mapex.sensor import Scan, integrate_scan


@dataclass
class ExplorerStats:
    """Counters kept for the run record."""

    replans: int = 0
    path_repairs: int = 0
    goals: list[tuple[int, int, int]] = field(default_factory=list)  # (t, row, col)
    approach_goals: int = 0  # goals standing in for an unreachable frontier point
    degraded_steps: list[int] = field(default_factory=list)  # re-plans lacking members
    fallback_steps: list[int] = field(default_factory=list)  # of those, scored on O_t only
    # (t, who answered each member) of every re-plan prediction served by remote workers
    member_workers: list[tuple[int, dict[str, str]]] = field(default_factory=list)


class Explorer:
    """Observed map + goal state machine for one robot."""

    def __init__(
        self,
        shape: tuple[int, int],
        method: Method,
        predictor: Predictor | None,
        config: ExplorationConfig,
        seed: int,
    ) -> None:
        if method.uses_prediction and predictor is None:
            raise ValueError(f"method '{method.name}' needs a predictor")
        self.method = method
        self.fallback = ObservedMap(config)
        self.predictor = predictor
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.observed = new_observed_map(shape)
        self.pose = np.zeros(2, dtype=np.int64)
        self.goal: np.ndarray | None = None
        self.goal_frontier: np.ndarray | None = None  # the frontier point the goal serves
        self.goal_is_approach = False  # reached only by standing on it (docs/algorithms.md#goals)
        self.path: np.ndarray | None = None
        self.scanned_from = np.zeros(shape, dtype=bool)  # cells the robot has scanned from
        self.end_reason: str | None = None  # "explored" or "unreachable" once it gives up
        self.prediction: EnsemblePrediction | None = None
        self.frontiers = np.zeros((0, 2), dtype=np.int64)
        self.frontier_scores: np.ndarray | None = None  # the method's, when it scores frontiers
        self.steps_since_plan = 0
        self.moved_since_goal = False
        self.stats = ExplorerStats()

    def observe(self, scan: Scan, seen: np.ndarray | None = None) -> None:
        """Integrate a LiDAR scan into O_t (and mark its cells in the bool map `seen`, when
        given); the scan's pose is the robot's pose."""
        integrate_scan(self.observed, scan, self.config.sensor, seen)
        self.pose = np.asarray(scan.pose, dtype=np.int64)
        self.scanned_from[self.pose[0], self.pose[1]] = True

    def next_motion(self, t: int) -> np.ndarray | None:
        """The cells (k, 2) to drive through at step `t`, or None when exploration is over."""
        if self.goal is not None and self._goal_done():
            self.goal = self.path = None
        if self.goal is not None and not path_is_clear(
            self.observed, self.path, self.config.navigation
        ):
            self._repair_path()
        if self.goal is None:
            self.replan(t)
        if self.goal is None:
            return None
        moved, self.path = advance_along_path(self.path, self.config.motion.cells_per_step)
        self.steps_since_plan += 1
        self.moved_since_goal = self.moved_since_goal or len(moved) > 0
        return moved

    def _goal_done(self) -> bool:
        nav = self.config.navigation
        distance = float(np.hypot(*(self.goal - self.pose)))
        near = self.moved_since_goal and distance <= nav.goal_reached_cells
        if (near and not self.goal_is_approach) or len(self.path) <= 1:
            return True
        period = self.method.replan_every_steps
        if period is not None and self.steps_since_plan >= period:
            return True
        if self.method.drop_goal_without_unknown:
            served = self.goal if self.goal_frontier is None else self.goal_frontier
            return not unknown_within(self.observed, served, nav.goal_unknown_radius_cells)
        return False

    def _repair_path(self) -> None:
        """New walls block the path: plan again to the same goal, or drop it if unreachable."""
        self.stats.path_repairs += 1
        cost = cost_map(self.observed, self.config.navigation)
        self.path = plan_path(self.observed, cost, self._cell(self.pose), self._cell(self.goal))
        if self.path is None:
            self.goal = None

    def replan(self, t: int) -> None:
        """Predict, score the frontiers and set a new goal and path (or the end reason)."""
        self.stats.replans += 1
        self.prediction = self.predict() if self.method.uses_prediction else None
        method = self._method_for(t, self.prediction)
        clusters = frontier_clusters(self.observed, self.config.frontier)
        self.frontiers = clusters.points
        cost = cost_map(self.observed, self.config.navigation)
        context = PlanningContext(
            observed=self.observed,
            pose=self.pose,
            frontiers=self.frontiers,
            prediction=self.prediction,
            cost=cost,
            reachable=reachable_mask(cost, self._cell(self.pose)),
            config=self.config,
            rng=self.rng,
            clusters=clusters,
            scanned_from=self.scanned_from,
        )
        goal = method.select_goal(context)
        if goal is None and self.config.frontier.small_clusters_last:
            small = frontier_clusters(self.observed, self.config.frontier, small=True)
            if len(small):
                context = replace(context, frontiers=small.points, clusters=small)
                self.frontiers = small.points
                goal = method.select_goal(context)
        self.frontier_scores = method.last_scores
        path = None
        if goal is not None:
            path = plan_path(self.observed, cost, self._cell(self.pose), self._cell(goal.cell))
        if path is None:
            self.end_reason = "explored" if len(context.frontiers) == 0 else "unreachable"
            return
        self._set_goal(t, goal, path)

    def _set_goal(self, t: int, goal: Goal, path: np.ndarray) -> None:
        self.goal, self.path = np.asarray(goal.cell, dtype=np.int64), path
        self.goal_frontier = goal.frontier
        self.goal_is_approach = goal.approach
        self.end_reason = None
        self.steps_since_plan = 0
        self.moved_since_goal = False
        self.stats.goals.append((t, int(self.goal[0]), int(self.goal[1])))
        self.stats.approach_goals += int(goal.approach)

    def _method_for(self, t: int, prediction: EnsemblePrediction | None) -> Method:
        """The method, or the observed-map fallback when too few members answered: a method
        of G_1..G_n's variance needs two of them, one of G's map alone needs G."""
        if prediction is not None and prediction.workers is not None:
            self.stats.member_workers.append((t, prediction.served_by()))
        wanted = self.method.prediction_members(self.predictor.n_members) if prediction else ()
        if prediction is None or len(prediction.answered) == len(wanted):
            return self.method
        self.stats.degraded_steps.append(t)
        enough = prediction.has_variance if self.method.reads_members else 0 in prediction.answered
        if enough:
            return self.method
        self.stats.fallback_steps.append(t)
        return self.fallback

    def predict(self) -> EnsemblePrediction:
        """The members the method reads, on the region that matters: known area plus sensor
        range."""
        region = known_region(self.observed, self.config.sensor.range_cells)
        members = self.method.prediction_members(self.predictor.n_members)
        return self.predictor.predict(self.observed, region, members)

    @staticmethod
    def _cell(cell: np.ndarray) -> Cell:
        return (int(cell[0]), int(cell[1]))
