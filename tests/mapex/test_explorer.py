"""The goal-keeping and re-planning rule of SPEC §3, on hand-made maps."""

import numpy as np
import pytest

from mapex.config import ExplorationConfig
from mapex.episode import run_episode
from mapex.explorer import Explorer
from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.methods import METHODS, make_method
from mapex.methods.base import Method
from mapex.prediction import make_predictor
from mapex.prediction.base import Predictor
from mapex.worlds import load_world


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


class _RecordingPool(_PartialPool):
    """Every member answers; the members of each request are recorded."""

    def __init__(self) -> None:
        super().__init__((0, 1, 2, 3))
        self.asked: list[tuple[int, ...]] = []

    def predict(self, observed, region=None, members=None):
        self.asked.append(tuple(members))
        return super().predict(observed, region, members)


@pytest.mark.parametrize(
    ("method", "members"),
    [
        ("mapex", (1, 2, 3)),
        ("no_visibility", (1, 2, 3)),
        ("mapex_path", (1, 2, 3)),
        ("mapex_plus", (1, 2, 3)),
        ("upen", (1, 2, 3)),
        ("no_variance", (0,)),
        ("ig_hector", (0,)),
        ("deterministic", (0, 1, 2, 3)),
    ],
)
def test_a_replan_predicts_only_the_members_its_method_reads(method, members):
    explorer = explorer_in_corridor()
    explorer.method = make_method(method, ExplorationConfig())
    explorer.predictor = _RecordingPool()
    assert explorer.next_motion(7) is not None
    assert explorer.predictor.asked == [members]
    assert explorer.stats.degraded_steps == []


@pytest.mark.parametrize(("answering", "fallback"), [((0,), False), ((1, 2, 3), True)])
def test_a_method_of_gs_map_alone_needs_g(answering, fallback):
    explorer = explorer_in_corridor()
    explorer.method = make_method("no_variance", ExplorationConfig())
    explorer.predictor = _PartialPool(answering)
    assert explorer.next_motion(7) is not None
    assert explorer.stats.degraded_steps == ([7] if fallback else [])
    assert explorer.stats.fallback_steps == ([7] if fallback else [])


@pytest.mark.parametrize("method", sorted(name for name, m in METHODS.items() if m.uses_prediction))
def test_predicting_only_the_members_read_changes_no_run(method, monkeypatch):
    """The rows a method does not read never reach its choices: the same run as when every
    member is predicted (classical ensemble, seeded)."""
    world, config = load_world("generated:1"), ExplorationConfig(steps=150)
    predictor = make_predictor("classical")
    lean = run_episode(world, method, predictor, 0, 0, config)
    monkeypatch.setattr(Method, "prediction_members", lambda self, n: tuple(range(n)))
    full = run_episode(world, method, predictor, 0, 0, config)
    np.testing.assert_array_equal(lean.trajectory, full.trajectory)
    assert lean.curves.coverage == full.curves.coverage
