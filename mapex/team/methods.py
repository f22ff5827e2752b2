"""Team methods: a single-robot frontier scorer made to coordinate through claims.

`TeamScorer` wraps any `FrontierScorer` (docs/algorithms.md#teams):

* `mapex_team`: MapEx's gain without the cells teammates have claimed (the visible sets of
  their goals), per unit distance; it claims its goal's visible set in turn;
* `mapex_plus_team`: the same discount on this project's best single-robot scorer;
* `nearest_team`: the nearest frontier not within `team.goal_exclusion_cells` (2 m) of a
  teammate's goal (the classic baseline); it claims its goal only;
* `mapex_independent`: MapEx on the shared map with no claims (the ablation that shows
  what coordination buys).

Frontiers a wrapper rules out score -inf, so they are tried last, not never: a robot with
nothing else left still goes there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from mapex.config import ConfigError, ExplorationConfig
from mapex.grid import UNKNOWN, Cell
from mapex.methods import METHODS
from mapex.methods.base import FrontierScorer, PlanningContext
from mapex.methods.goals import Goal
from mapex.methods.information_gain import MapEx, known_walls
from mapex.methods.nearest import NearestFrontier
from mapex.methods.path_gain import MapExPlus
from mapex.navigation import plan_path
from mapex.team.claims import Claim, claimed_cells
from mapex.visibility import visible_mask


class TeamScorer(FrontierScorer):
    """`inner` with teammates' claims taken into account (module doc).

    The team loop sets `teammates` (their current claims) before each re-plan; after one,
    `claim_of(robot, t)` is what this robot tells them (None when it does not claim).
    """

    def __init__(
        self,
        config: ExplorationConfig,
        inner: FrontierScorer,
        name: str,
        discount_claims: bool = False,
        avoid_claimed_goals: bool = False,
    ) -> None:
        super().__init__(config)
        self.inner = inner
        self.name = name
        self.uses_prediction = inner.uses_prediction
        self.replan_every_steps = inner.replan_every_steps
        self.discount_claims = discount_claims
        self.avoid_claimed_goals = avoid_claimed_goals
        self.teammates: list[Claim] = []
        self._last: tuple[Goal, float, PlanningContext] | None = None

    @property
    def claims(self) -> bool:
        """Whether this method tells teammates its goals."""
        return self.discount_claims or self.avoid_claimed_goals

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
        """The claim of the last goal chosen, or None (no goal, or a method that does not
        claim)."""
        if not self.claims or self._last is None:
            return None
        goal, score, context = self._last
        cell = (int(goal.cell[0]), int(goal.cell[1]))
        visible = np.zeros(context.observed.shape, dtype=bool)
        if self.discount_claims:
            visible = self._visible_set(context, self._claimed_viewpoints(context, goal))
        return Claim(robot, t, cell, score, visible)

    def _near_claimed_goals(self, frontiers: np.ndarray) -> np.ndarray:
        goals = np.asarray([claim.goal for claim in self.teammates], dtype=np.float64)
        offsets = frontiers[:, None, :].astype(np.float64) - goals[None, :, :]
        nearest = np.hypot(offsets[..., 0], offsets[..., 1]).min(axis=1)
        return nearest < self.config.team.goal_exclusion_cells

    def _claimed_viewpoints(self, context: PlanningContext, goal: Goal) -> list[Cell]:
        """The goal's frontier point, and with `team.claim_path_every_cells` = k > 0 every
        k-th cell of the path there (the robot scans on its way, so teammates should not
        count those cells either)."""
        points: list[Cell] = [(int(goal.frontier[0]), int(goal.frontier[1]))]
        every = self.config.team.claim_path_every_cells
        if every > 0:
            pose = (int(context.pose[0]), int(context.pose[1]))
            path = plan_path(context.observed, context.cost, pose, goal.cell)
            if path is not None:
                points += [(int(r), int(c)) for r, c in path[every::every]]
        return points

    def _visible_set(self, context: PlanningContext, points: list[Cell]) -> np.ndarray:
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


def _team(
    inner: type[FrontierScorer], name: str, **options: bool
) -> Callable[[ExplorationConfig], TeamScorer]:
    return lambda config: TeamScorer(config, inner(config), name, **options)


TEAM_METHODS: dict[str, Callable[[ExplorationConfig], TeamScorer]] = {
    "mapex_team": _team(MapEx, "mapex_team", discount_claims=True),
    "mapex_plus_team": _team(MapExPlus, "mapex_plus_team", discount_claims=True),
    "nearest_team": _team(NearestFrontier, "nearest_team", avoid_claimed_goals=True),
    "mapex_independent": _team(MapEx, "mapex_independent"),
}


ALL_METHODS: tuple[str, ...] = (*sorted(METHODS), *sorted(TEAM_METHODS))  # --method choices


def make_team_method(name: str, config: ExplorationConfig) -> TeamScorer:
    """The team method called `name` (ValueError with the choices otherwise)."""
    if name not in TEAM_METHODS:
        raise ValueError(f"unknown team method '{name}' (choose from: {', '.join(TEAM_METHODS)})")
    return TEAM_METHODS[name](config)


def check_team_flags(method: str, robots: int) -> bool:
    """Whether the run is a team's; ConfigError (one line) for a bad --robots/--method pair."""
    if robots < 1:
        raise ConfigError(f"--robots must be at least 1 (got {robots})")
    if robots > 1 and method not in TEAM_METHODS:
        raise ConfigError(
            f"--robots {robots} needs a team method ({', '.join(TEAM_METHODS)}), not {method}"
        )
    return method in TEAM_METHODS
