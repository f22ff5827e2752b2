"""The goal-keeping and re-planning rule of SPEC §3, on hand-made maps."""

import numpy as np
import pytest

from mapex.config import ExplorationConfig
from mapex.explorer import Explorer
from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.methods import make_method
from mapex.prediction.base import Predictor


def explorer_in_corridor() -> Explorer:
    """A known corridor (rows 10-20) open to unknown space at its right end (col 60)."""
    config = ExplorationConfig()
    explorer = Explorer((31, 80), make_method("nearest", config), None, config, seed=0)
    explorer.observed[9, :61] = OCCUPIED
    explorer.observed[21, :61] = OCCUPIED
    explorer.observed[10:21, :61] = FREE
    explorer.pose = np.array([15, 5])
    return explorer


def test_first_motion_plans_to_the_frontier_and_moves_three_cells():
    explorer = explorer_in_corridor()
    moved = explorer.next_motion(0)
    assert explorer.stats.replans == 1
    assert explorer.goal[1] == 60  # the frontier at the open end
    assert len(moved) == 3
    assert np.abs(np.diff(np.vstack([explorer.pose, moved]), axis=0)).max() == 1


def test_goal_is_kept_while_it_is_worth_going_to():
    explorer = explorer_in_corridor()
    for t in range(5):
        moved = explorer.next_motion(t)
        explorer.pose = moved[-1]
    assert explorer.stats.replans == 1


def test_goal_is_dropped_when_no_unknown_cell_remains_near_it():
    explorer = explorer_in_corridor()
    explorer.pose = explorer.next_motion(0)[-1]
    explorer.observed[explorer.observed == UNKNOWN] = OCCUPIED  # all else seen: solid rock
    explorer.observed[10:21, 61:75] = FREE  # the space behind the goal, closed by walls
    assert explorer.next_motion(1) is None  # no frontier left: exploration is over
    assert explorer.stats.replans == 2 and explorer.end_reason == "explored"


@pytest.mark.parametrize("approach", [True, False])
def test_an_approach_goal_is_kept_until_the_robot_stands_on_it(approach):
    explorer = explorer_in_corridor()
    explorer.pose = np.array([15, 45])
    explorer.goal = np.array([15, 50])
    explorer.goal_frontier = np.array([15, 60]) if approach else explorer.goal
    explorer.goal_is_approach = approach
    explorer.path = np.array([[15, c] for c in range(45, 51)])
    explorer.moved_since_goal = True  # 0.5 m from the goal: near enough for a frontier point
    moved = explorer.next_motion(3)
    assert explorer.stats.replans == (0 if approach else 1)
    if approach:
        np.testing.assert_array_equal(moved[-1], [15, 48])


def test_a_new_wall_on_the_path_makes_the_planner_repair_it():
    explorer = explorer_in_corridor()
    explorer.pose = explorer.next_motion(0)[-1]
    ahead = explorer.path[len(explorer.path) // 2]
    explorer.observed[ahead[0], ahead[1] - 1 : ahead[1] + 2] = OCCUPIED  # a pillar on the path
    explorer.next_motion(1)
    assert explorer.stats.path_repairs == 1
    assert not (explorer.observed[explorer.path[:, 0], explorer.path[:, 1]] == OCCUPIED).any()


def test_unknown_everywhere_but_the_robot_cell_gives_no_motion():
    config = ExplorationConfig()
    explorer = Explorer((10, 10), make_method("nearest", config), None, config, seed=0)
    explorer.observed[5, 5] = FREE
    explorer.pose = np.array([5, 5])
    assert (explorer.observed == UNKNOWN).sum() == 99
    assert explorer.next_motion(0) is None  # a single free cell is no frontier cluster


class _PartialPool(Predictor):
    """A pool where only `answering` members answer (the others' workers are gone)."""

    n_members = 4

    def __init__(self, answering: tuple[int, ...]) -> None:
        self.answering = answering

    def predict_members(self, observed, members):
        return np.full((len(members), *observed.shape), 0.3, dtype=np.float32)

    def predict(self, observed, region=None, members=None):
        asked = tuple(range(self.n_members)) if members is None else tuple(members)
        return super().predict(observed, region, [k for k in asked if k in self.answering])


@pytest.mark.parametrize(
    ("answering", "degraded", "fallback"),
    [((0, 1, 2, 3), False, False), ((0, 2, 3), True, False), ((1,), True, True), ((), True, True)],
)
def test_missing_members_are_recorded_and_too_few_fall_back_to_observed_map_scoring(
    answering, degraded, fallback
):
    config = ExplorationConfig()
    explorer = explorer_in_corridor()
    explorer.method = make_method("mapex", config)
    explorer.predictor = _PartialPool(answering)
    assert explorer.next_motion(7) is not None and explorer.goal[1] == 60
    assert explorer.stats.degraded_steps == ([7] if degraded else [])
    assert explorer.stats.fallback_steps == ([7] if fallback else [])
    assert explorer.frontier_scores is not None and len(explorer.frontier_scores) == 1
