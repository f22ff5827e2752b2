"""The common interface of every exploration method (docs/algorithms.md#methods).

All methods share the exploration loop and differ only in how they pick the
next goal. Most score frontiers (`FrontierScorer`: higher is better, the best
*reachable* frontier wins); UPEN picks a goal of its own (`Method`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from mapex.config import ExplorationConfig
from mapex.frontiers import FrontierClusters
from mapex.grid import FREE, UNKNOWN
from mapex.methods.claims import Claim
from mapex.methods.goals import Goal, cluster_goal
from mapex.methods.teammates import TeamView
from mapex.navigation import plan_path
from mapex.prediction.base import EnsemblePrediction


@dataclass(frozen=True)
class PlanningContext:
    """Everything a method may look at when the planner re-plans.

    observed: uint8 observed map O_t; pose: robot cell (row, col);
    frontiers: int (K, 2) frontier points; prediction: the ensemble (None for
    methods that use none); cost: float32 planning cost map (inf = blocked);
    reachable: bool map of cells the robot can drive to; clusters: the frontier
    clusters the points stand for (None: each point is a cluster of its own);
    scanned_from: bool map of the cells the robot has scanned from (None: its pose only);
    claimed: bool map of the cells teammates' goals will see (None: alone, or no claims):
    they are worth nothing here (docs/algorithms.md#teams).
    """

    observed: np.ndarray
    pose: np.ndarray
    frontiers: np.ndarray
    prediction: EnsemblePrediction | None
    cost: np.ndarray
    reachable: np.ndarray
    config: ExplorationConfig
    rng: np.random.Generator
    clusters: FrontierClusters | None = None
    scanned_from: np.ndarray | None = None
    claimed: np.ndarray | None = None

    def frontier_distances(self) -> np.ndarray:
        """Euclidean distance in cells from the robot to each frontier, at least 1."""
        offsets = self.frontiers.astype(np.float64) - self.pose.astype(np.float64)
        return np.maximum(np.hypot(offsets[:, 0], offsets[:, 1]), 1.0)

    def unknown_weights(self, values: np.ndarray | float) -> np.ndarray:
        """float32 map: `values` on unknown cells, 0 on known ones (not in any visible set)
        and on cells teammates have claimed."""
        worth = self.observed == UNKNOWN
        if self.claimed is not None:
            worth &= ~self.claimed
        return np.where(worth, values, 0).astype(np.float32)

    def can_reach(self, cell: np.ndarray) -> bool:
        """Whether A* finds a path from the robot to this known-free cell.

        A passable cell is decided by the reachability map; a free goal inside the wall
        inflation (which A* may still enter as its last cell) by A* itself, when one of
        its neighbours is reachable.
        """
        row, col = int(cell[0]), int(cell[1])
        if self.observed[row, col] != FREE:
            return False
        if self.reachable[row, col]:
            return True
        window = self.reachable[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2]
        if not window.any():
            return False
        pose = (int(self.pose[0]), int(self.pose[1]))
        return plan_path(self.observed, self.cost, pose, (row, col)) is not None

    def cluster_members(self, index: int) -> np.ndarray:
        """int64 (n, 2) frontier cells of the cluster of frontier point `index`."""
        if self.clusters is None:
            return self.frontiers[index : index + 1].astype(np.int64)
        return self.clusters.members(index)

    def was_scanned_from(self, cell: np.ndarray) -> bool:
        """Whether the robot has already scanned from `cell` (its pose included)."""
        row, col = int(cell[0]), int(cell[1])
        if (row, col) == (int(self.pose[0]), int(self.pose[1])):
            return True
        return self.scanned_from is not None and bool(self.scanned_from[row, col])


class Method(ABC):
    """A goal selector. `select_goal` returns a reachable goal, or None when done."""

    name: str = ""
    uses_prediction: bool = False
    # Which rows of the ensemble prediction the method reads: G's map P_t (`main`) and/or
    # the mean and variance of G_1..G_n (`members`). A re-plan asks only for those.
    reads_main: bool = True
    reads_members: bool = True
    replan_every_steps: int | None = None  # re-plan periodically even if the goal is kept
    # the goal-keeping rule of docs/algorithms.md#goals; UPEN's goals are not frontiers
    drop_goal_without_unknown: bool = True
    # In a team (docs/algorithms.md#teams): whether the method tells teammates its goals
    # and heeds theirs; one that does not runs independently on the team's shared map.
    coordinates: bool = False
    # Whether the method was made for teams: its records carry the team's size and fields
    # even for a team of one (their names end in -team<N>).
    made_for_teams: bool = False

    def __init__(self, config: ExplorationConfig) -> None:
        self.config = config
        self.last_scores: np.ndarray | None = None  # per frontier of the last choice, if scored
        self.teammates: list[Claim] = []  # their claims, set by the team before each re-plan
        self.team_view: TeamView | None = None  # their poses, set by the team at each step
        self.waiting = False  # the last choice was to wait: teammates have the work for now

    @abstractmethod
    def select_goal(self, context: PlanningContext) -> Goal | None:
        """The next goal, or None when there is nothing left to explore."""

    def prediction_members(self, n_members: int) -> tuple[int, ...]:
        """The ensemble members a re-plan must predict (member 0 is G): only the rows the
        method reads, so no forward pass is spent on a map it never looks at."""
        main = (0,) if self.reads_main else ()
        members = tuple(range(1, n_members)) if self.reads_members else ()
        return main + members

    def claim_of(self, robot: int, t: int) -> Claim | None:
        """What robot `robot` tells its teammates after re-planning at step `t` (None: a
        method that does not coordinate, or no goal)."""
        return None

    def replans_at(self, t: int) -> bool:
        """Whether the robot drops its goal and re-plans at step `t` whatever its state (a
        team's re-plan in step); by default only when its goal ends."""
        return False


class FrontierScorer(Method):
    """A method that scores frontier points; the best-scored cluster with a goal wins.

    Clusters are tried in score order, those the method cannot score (not finite, e.g. an
    unreachable point's path cost) last, so a run ends only when no cluster has a goal.
    """

    @abstractmethod
    def score(self, context: PlanningContext) -> np.ndarray:
        """float64 (K,) score per frontier, higher is better."""

    def select_goal(self, context: PlanningContext) -> Goal | None:
        self.last_scores = None
        if len(context.frontiers) == 0:
            return None
        scores = self.score(context)
        self.last_scores = scores
        ranked = np.where(np.isfinite(scores), -scores, np.inf)
        for index in np.argsort(ranked, kind="stable"):
            goal = cluster_goal(context, int(index))
            if goal is not None:
                return goal
        return None
