"""Methods that coordinate a team through claims (docs/algorithms.md#teams).

`Coordinated` wraps a single-robot `FrontierScorer`: `mapex_team` and `mapex_plus_team`
discount the cells teammates have claimed and claim their goal's visible set in turn;
`nearest_team` keeps away from teammates' goals and claims its goal only. Frontiers a
wrapper rules out score -inf, so they are tried last, not never. Any other method in a
team runs independently on the shared map; `mapex_independent` is MapEx under the name
the team ablation is reported by.
"""

from __future__ import annotations

from dataclasses import replace
from typing import ClassVar

import numpy as np

from mapex.config import ExplorationConfig
from mapex.grid import UNKNOWN, Cell
from mapex.methods.base import FrontierScorer, PlanningContext
from mapex.methods.claims import Claim, claimed_cells
from mapex.methods.goals import Goal
from mapex.methods.information_gain import MapEx, known_walls
from mapex.methods.nearest import NearestFrontier
from mapex.methods.path_gain import MapExPlus
from mapex.navigation import plan_path
from mapex.visibility import visible_mask


class Coordinated(FrontierScorer):
    """`scorer`'s scores with teammates' claims taken into account (module doc).

    The team sets `teammates` (their current claims) before each re-plan; after one,
    `claim_of(robot, t)` is what this robot tells them.
    """

    scorer: ClassVar[type[FrontierScorer]]  # the single-robot method it wraps
    discount_claims: ClassVar[bool] = False  # claimed cells are worth nothing here
    avoid_claimed_goals: ClassVar[bool] = False  # frontiers near claimed goals go last
    coordinates = True
    made_for_teams = True

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        cls.uses_prediction = cls.scorer.uses_prediction
        cls.replan_every_steps = cls.scorer.replan_every_steps

    def __init__(self, config: ExplorationConfig) -> None:
        super().__init__(config)
        self.inner = self.scorer(config)
        self._last: tuple[Goal, float, PlanningContext] | None = None

    def score(self, context: PlanningContext) -> np.ndarray:
        if self.discount_claims and self.teammates:
            claimed = claimed_cells(self.teammates, context.observed.shape)
            context = replace(context, claimed=claimed)
        scores = np.asarray(self.inner.score(context), dtype=np.float64)
        if self.avoid_claimed_goals and self.teammates and len(scores):
            scores = np.where(self._near_claimed_goals(context.frontiers), -np.inf, scores)
        return scores

    def select_goal(self, context: PlanningContext) -> Goal | None:
        goal = super().select_goal(context)
        self._last = None
        if goal is not None and goal.frontier is not None and self.last_scores is not None:
            index = int(np.flatnonzero((context.frontiers == goal.frontier).all(axis=1))[0])
            self._last = (goal, float(self.last_scores[index]), context)
        return goal

    def claim_of(self, robot: int, t: int) -> Claim | None:
        """The claim of the last goal chosen, or None (no goal)."""
        if self._last is None:
            return None
        goal, score, context = self._last
        cell = (int(goal.cell[0]), int(goal.cell[1]))
        visible = np.zeros(context.observed.shape, dtype=bool)
        if self.discount_claims:
            visible = claimed_visible_set(context, goal)
        return Claim(robot, t, cell, score, visible)

    def _near_claimed_goals(self, frontiers: np.ndarray) -> np.ndarray:
        goals = np.asarray([claim.goal for claim in self.teammates], dtype=np.float64)
        offsets = frontiers[:, None, :].astype(np.float64) - goals[None, :, :]
        nearest = np.hypot(offsets[..., 0], offsets[..., 1]).min(axis=1)
        return nearest < self.config.team.goal_exclusion_cells


def claimed_visible_set(context: PlanningContext, goal: Goal) -> np.ndarray:
    """bool (rows, cols): what a robot going to `goal` claims, the unknown cells seen from
    its viewpoints (`claimed_viewpoints`)."""
    return visible_unknown(context, claimed_viewpoints(context, goal))


def claimed_viewpoints(context: PlanningContext, goal: Goal) -> list[Cell]:
    """The goal's frontier point, and with `team.claim_path_every_cells` = k > 0 every
    k-th cell of the path there (the robot scans on its way, so teammates should not
    count those cells either)."""
    points: list[Cell] = [(int(goal.frontier[0]), int(goal.frontier[1]))]
    every = context.config.team.claim_path_every_cells
    if every > 0:
        pose = (int(context.pose[0]), int(context.pose[1]))
        path = plan_path(context.observed, context.cost, pose, goal.cell)
        if path is not None:
            points += [(int(r), int(c)) for r, c in path[every::every]]
    return points


def visible_unknown(context: PlanningContext, points: list[Cell]) -> np.ndarray:
    """The unknown cells MapEx's rays from `points` reach (on M_t, or on the observed
    map's walls without a prediction)."""
    cfg = context.config.visibility
    if context.prediction is not None:
        opacity, rule, epsilon = context.prediction.mean, cfg.stop_rule, cfg.epsilon
    else:
        opacity = known_walls(context)
        rule, epsilon = "threshold", 0.5
    seen = np.zeros(context.observed.shape, dtype=bool)
    for point in points:
        seen |= visible_mask(opacity, point, cfg.n_rays, cfg.range_cells, rule, epsilon)
    return seen & (context.observed == UNKNOWN)


class MapExTeam(Coordinated):
    name = "mapex_team"
    scorer = MapEx
    discount_claims = True


class MapExPlusTeam(Coordinated):
    name = "mapex_plus_team"
    scorer = MapExPlus
    discount_claims = True


class NearestTeam(Coordinated):
    name = "nearest_team"
    scorer = NearestFrontier
    avoid_claimed_goals = True


class MapExIndependent(MapEx):
    """MapEx, named for the team ablation: what coordination buys over none."""

    name = "mapex_independent"
    made_for_teams = True
