"""`mapex_assign`: robots assigned to frontiers jointly, on path costs, with MapEx's gain
made smaller near the goals teammates hold (docs/algorithms.md#teams).

A robot re-planning with teammates solves the assignment of the robots that are free to
choose: itself and, when every robot re-plans (at t = 0, and at the steps t with
t % `team.assign_every_steps` == 0), all of them. Teammates holding a claim hold its goal
(a waiting teammate holds none and takes what is left when it looks again): a frontier within
`team.goal_exclusion_cells` of such a goal is taken, and one further away is worth its MapEx
gain scaled linearly up to full at `team.assign_discount_cells` (the diminishing utility of
Burgard et al., T-RO 2005). The Hungarian method (`scipy.optimize.linear_sum_assignment`)
gives the free robots the frontiers of the largest summed utility, a frontier's worth per
unit of the robot's path cost (a Dijkstra from each free robot's pose on the planning cost
map); with several free robots only the best frontier of each `goal_exclusion_cells`
neighbourhood is offered, so no two go to the same place. Every robot computes the same
assignment from the shared map, prediction and poses (`mapex.methods.teammates`), so no
message is needed to agree on it. A robot left without a frontier waits (teammates have
the work) and looks again after `team.idle_replan_steps`. Alone it is `mapex`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from mapex.config import ExplorationConfig
from mapex.grid import Cell
from mapex.methods.base import PlanningContext
from mapex.methods.claims import Claim, claimed_cells
from mapex.methods.coordinated import claimed_visible_set
from mapex.methods.goals import Goal, cluster_goal
from mapex.methods.information_gain import MapEx, mapex_gain
from mapex.methods.paths import frontier_paths
from mapex.methods.teammates import TeamView


def goal_discount(
    frontiers: np.ndarray, goals: list[Cell], taken_cells: float, full_cells: float
) -> np.ndarray:
    """float64 (K,): what each frontier is still worth, as a share of its gain, given the
    goals teammates hold: 0 within `taken_cells` of one, 1 from `full_cells` on, linear in
    between (all 1 without goals)."""
    if not goals or len(frontiers) == 0:
        return np.ones(len(frontiers))
    offsets = frontiers[:, None, :].astype(np.float64) - np.asarray(goals, np.float64)[None]
    nearest = np.hypot(offsets[..., 0], offsets[..., 1]).min(axis=1)
    return np.clip((nearest - taken_cells) / max(full_cells - taken_cells, 1.0), 0.0, 1.0)


def spread_targets(
    frontiers: np.ndarray, worth: np.ndarray, eligible: np.ndarray, apart_cells: float
) -> np.ndarray:
    """int64: the eligible frontiers, best worth first (ties: lower index), each kept only
    when at least `apart_cells` from every one kept before it."""
    kept: list[int] = []
    for index in np.argsort(-worth, kind="stable"):
        if not eligible[index]:
            continue
        if kept:
            gaps = np.hypot(*(frontiers[kept] - frontiers[index]).astype(np.float64).T)
            if gaps.min() < apart_cells:
                continue
        kept.append(int(index))
    return np.asarray(kept, dtype=np.int64)


def assign(utility: np.ndarray) -> dict[int, int]:
    """row -> column of the assignment of largest summed utility (float (rows, cols), -inf:
    not allowed); rows left without an allowed column are absent."""
    allowed = np.isfinite(utility)
    if not allowed.any():
        return {}
    # a forbidden pair costs more than every allowed one together: it is used only when a
    # row has no allowed column left, and then dropped
    floor = -(np.abs(utility[allowed]).sum() + 1.0)
    rows, cols = linear_sum_assignment(np.where(allowed, utility, floor), maximize=True)
    return {int(r): int(c) for r, c in zip(rows, cols, strict=True) if allowed[r, c]}


class MapExAssign(MapEx):
    """MapEx's gain, robots assigned to frontiers jointly (module doc)."""

    name = "mapex_assign"
    coordinates = True
    made_for_teams = True

    def __init__(self, config: ExplorationConfig) -> None:
        super().__init__(config)
        self._chosen: tuple[Goal, float, PlanningContext] | None = None  # goal, score, context

    def replans_at(self, t: int) -> bool:
        every = self.config.team.assign_every_steps
        view = self.team_view
        return every > 0 and t % every == 0 and view is not None and not view.alone

    def select_goal(self, context: PlanningContext) -> Goal | None:
        self.waiting, self._chosen = False, None
        view = self.team_view
        if view is None or view.alone or len(context.frontiers) == 0:
            goal = super().select_goal(context)
            if goal is not None and self.last_scores is not None:
                index = int(np.flatnonzero((context.frontiers == goal.frontier).all(axis=1))[0])
                self._chosen = (goal, float(self.last_scores[index]), context)
            return goal
        return self._assigned_goal(context, view)

    def _assigned_goal(self, context: PlanningContext, view: TeamView) -> Goal | None:
        team = self.config.team
        frontiers = context.frontiers
        everyone = view.t == 0 or self.replans_at(view.t)  # every robot re-plans now
        free = view.live if everyone else [view.robot]
        claims = [c for c in self.teammates if c.robot not in free and c.robot in view.live]
        held = [claim.goal for claim in claims]
        discounted: tuple[int, ...] = ()  # whose claimed cells the gain leaves out
        if team.assign_claims_visible and claims:
            context = replace(context, claimed=claimed_cells(claims, context.observed.shape))
            discounted = tuple(claim.robot for claim in claims)
        key = ("mapex_gain", frontiers.tobytes(), discounted)
        gains = view.shared(key, lambda: mapex_gain(context))
        near, far = team.goal_exclusion_cells, team.assign_discount_cells
        share = goal_discount(frontiers, held, near, far)
        worth = gains * share
        open_ = share > 0
        costs = np.stack([self._path_costs(context, view, robot) for robot in free])
        utility = np.where(
            open_ & np.isfinite(costs), worth / np.maximum(costs, 1.0), -np.inf
        )  # (free robots, K)
        me = free.index(view.robot)
        self.last_scores = utility[me]
        if len(free) > 1:
            offered = spread_targets(frontiers, worth, open_, team.goal_exclusion_cells)
        else:
            offered = np.flatnonzero(open_)
        pairs = assign(utility[:, offered])
        if me not in pairs:
            self.waiting = bool(held) or len(free) > 1  # teammates have the work
            return None
        target = int(offered[pairs[me]])
        others = {int(offered[c]) for r, c in pairs.items() if r != me}
        order = [target] + [
            int(i)
            for i in np.argsort(-utility[me], kind="stable")
            if np.isfinite(utility[me, i]) and int(i) != target and int(i) not in others
        ]
        for index in order:
            goal = cluster_goal(context, index)
            if goal is not None:
                self._chosen = (goal, float(utility[me, index]), context)
                return goal
        self.waiting = bool(held) or bool(others)
        return None

    @staticmethod
    def _path_costs(context: PlanningContext, view: TeamView, robot: int) -> np.ndarray:
        """float64 (K,): robot `robot`'s path cost to every frontier (inf: unreachable)."""
        pose = view.poses[robot]
        key = ("frontier_paths", pose, context.frontiers.tobytes())
        at = replace(context, pose=np.asarray(pose, dtype=np.int64))
        return view.shared(key, lambda: frontier_paths(at).cost)

    def claim_of(self, robot: int, t: int) -> Claim | None:
        """The goal chosen; its visible set is empty (teammates keep away from the goal
        itself) unless `team.assign_claims_visible`."""
        if self._chosen is None:
            return None
        goal, score, context = self._chosen
        cell = (int(goal.cell[0]), int(goal.cell[1]))
        if self.config.team.assign_claims_visible:
            visible = claimed_visible_set(context, goal)
        else:
            visible = np.zeros(context.observed.shape, dtype=bool)
        return Claim(robot, t, cell, score, visible)
