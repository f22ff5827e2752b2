"""The coordination of `mapex_assign` (robots assigned to frontiers jointly) and
`mapex_voronoi` (each robot in its own path-distance cell) on hand-made scenes: two robots
and two rooms split, one room sends one robot; their helpers; a team of one is `mapex`; the
team loop's re-plans in step and waiting robots."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mapex.config import ExplorationConfig, TeamConfig
from mapex.episode import run_episode
from mapex.frontiers import frontier_clusters
from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.methods import make_method
from mapex.methods.assignment import assign, goal_discount, spread_targets
from mapex.methods.base import PlanningContext
from mapex.methods.claims import Claim
from mapex.methods.regions import path_voronoi, region_cost
from mapex.methods.teammates import TeamView
from mapex.navigation import cost_map, reachable_mask
from mapex.prediction.base import EnsemblePrediction
from mapex.search import shortest_path_tree
from mapex.worlds import generate_floor_plan

CONFIG = ExplorationConfig()
SHAPE = (61, 121)
POSES = ((30, 52), (30, 68))  # robot 0 nearer the left end of the corridor, robot 1 the right


def corridor(left_open: bool) -> tuple[np.ndarray, EnsemblePrediction]:
    """A known corridor (rows 25-35, cols 35-85) walled above and below, open into unknown
    space at its right end and, when `left_open`, at its left end. The ensemble predicts
    a room beyond each open end, and disagrees more about the right one: a robot alone
    (MapEx) goes right from anywhere in the corridor."""
    observed = np.full(SHAPE, UNKNOWN, dtype=np.uint8)
    observed[[24, 36], 34:87] = OCCUPIED
    observed[25:36, 35:86] = FREE
    if not left_open:
        observed[24:37, 34] = OCCUPIED
    members = np.repeat((observed.astype(np.float32) / 2)[None], 4, axis=0)
    members[:, :, :34] = np.array([0.2, 0.4, 0.3, 0.5], np.float32)[:, None, None]  # left room
    members[:, :, 87:] = np.array([0.0, 0.6, 0.1, 0.7], np.float32)[:, None, None]  # right room
    known = observed != UNKNOWN
    members[:, known] = observed[known].astype(np.float32) / 2
    return observed, EnsemblePrediction(members)


def context(observed: np.ndarray, prediction: EnsemblePrediction, robot: int) -> PlanningContext:
    cost = cost_map(observed, CONFIG.navigation)
    clusters = frontier_clusters(observed, CONFIG.frontier)
    return PlanningContext(
        observed=observed, pose=np.array(POSES[robot]), frontiers=clusters.points,
        prediction=prediction, cost=cost, reachable=reachable_mask(cost, POSES[robot]),
        config=CONFIG, rng=np.random.default_rng(0), clusters=clusters,
    )  # fmt: skip


def choose(name: str, left_open: bool, robot: int, alone: bool = False, t: int = 0):
    """Robot `robot`'s goal (None: it waits) at step t with its teammate at its pose, or
    alone; and the method."""
    observed, prediction = corridor(left_open)
    method = make_method(name, CONFIG)
    poses = (POSES[robot],) if alone else POSES
    method.team_view = TeamView(0 if alone else robot, t, poses)
    return method.select_goal(context(observed, prediction, robot)), method


def side(goal) -> str:
    return "left" if goal.cell[1] < 60 else "right"


@pytest.mark.parametrize("name", ["mapex", "mapex_assign", "mapex_voronoi"])
def test_alone_both_robots_would_go_to_the_same_room(name):
    goals = [choose(name, True, robot, alone=True)[0] for robot in (0, 1)]
    assert [side(goal) for goal in goals] == ["right", "right"]


@pytest.mark.parametrize("name", ["mapex_assign", "mapex_voronoi"])
def test_two_robots_two_rooms_split(name):
    (left, _), (right, _) = (choose(name, True, robot) for robot in (0, 1))
    assert (side(left), side(right)) == ("left", "right")


@pytest.mark.parametrize("name", ["mapex_assign", "mapex_voronoi"])
def test_one_room_one_robot_goes_and_the_other_waits(name):
    (first, first_method), (second, second_method) = (choose(name, False, r) for r in (0, 1))
    assert first is None and first_method.waiting  # robot 0 is farther from the only room
    assert side(second) == "right" and not second_method.waiting


def test_later_a_re_planning_robot_does_not_leave_the_room_to_a_waiting_teammate():
    """A waiting teammate decides only when it looks again: if the robot whose goal ended
    left it the room, both could stand still and the team would end with work left."""
    goal, method = choose("mapex_assign", False, 0, t=7)  # robot 1 holds no claim: waits
    assert side(goal) == "right" and not method.waiting


def test_mapex_team_sends_both_robots_to_the_better_room():
    """Today's goal claims at the same step: each robot has not yet seen the other's."""
    goals = [choose("mapex_team", True, robot)[0] for robot in (0, 1)]
    assert [side(goal) for goal in goals] == ["right", "right"]


def test_an_assign_robot_keeps_off_a_goal_a_teammate_holds_and_claims_its_own():
    observed, prediction = corridor(left_open=True)
    method = make_method("mapex_assign", CONFIG)
    method.team_view = TeamView(1, 3, POSES)  # off step: robot 0 holds its goal
    right_end = (30, 85)
    method.teammates = [Claim(0, 2, right_end, 1.0, np.zeros(SHAPE, bool))]
    goal = method.select_goal(context(observed, prediction, 1))
    assert side(goal) == "left"  # the better room is taken, though robot 1 is nearer it
    claim = method.claim_of(1, 3)
    assert claim.goal == tuple(int(v) for v in goal.cell)
    assert claim.visible[:, :34].any() and not claim.visible[25:36, 35:86].any()  # unknown only


def test_an_assign_robot_leaves_the_cells_a_teammate_claimed_out_of_its_gain():
    observed, prediction = corridor(left_open=True)
    far_right = np.zeros(SHAPE, bool)
    far_right[:, 86:] = True  # robot 0 will see all of the right room
    gains = {}
    for visible in (False, True):
        config = replace(CONFIG, team=TeamConfig(assign_claims_visible=visible))
        method = make_method("mapex_assign", config)
        method.team_view = TeamView(1, 3, POSES)
        method.teammates = [Claim(0, 2, (10, 200), 1.0, far_right)]  # a goal far away
        method.select_goal(context(observed, prediction, 1))
        gains[visible] = method.last_scores
        assert method.claim_of(1, 3).visible.any() == visible  # its own claim: as configured
    right = int(np.argmax(context(observed, prediction, 1).frontiers[:, 1]))
    # what is left: the few cells of the left room seen along the corridor
    assert 0 < gains[True][right] < gains[False][right] / 10


def test_the_goal_discount_grows_linearly_from_taken_to_full():
    frontiers = np.array([[0, 0], [0, 10], [0, 20], [0, 40], [0, 100]])
    share = goal_discount(frontiers, [(0, 0)], taken_cells=10, full_cells=30)
    np.testing.assert_allclose(share, [0, 0, 0.5, 1, 1])
    assert goal_discount(frontiers, [], 10, 30).tolist() == [1] * 5


def test_targets_are_spread_best_first():
    frontiers = np.array([[0, 0], [0, 5], [0, 30], [0, 33]])
    worth = np.array([1.0, 2.0, 3.0, 3.0])
    kept = spread_targets(frontiers, worth, np.array([True, True, True, True]), 10)
    assert kept.tolist() == [2, 1]  # ties: the lower index; (0, 0) is 5 from (0, 5)
    eligible = np.array([True, False, True, True])
    assert spread_targets(frontiers, worth, eligible, 10).tolist() == [2, 0]


def test_the_assignment_maximises_the_summed_utility_and_skips_what_is_not_allowed():
    utility = np.array([[3.0, 2.0], [2.5, 0.1]])  # greedy would give robot 0 column 0: 3.1
    assert assign(utility) == {0: 1, 1: 0}  # 4.5
    assert assign(np.array([[1.0], [2.0]])) == {1: 0}  # one frontier: the better robot
    assert assign(np.array([[-np.inf, 1.0], [-np.inf, 2.0]])) == {1: 1}
    assert assign(np.full((2, 2), -np.inf)) == {}


def test_path_voronoi_is_the_nearest_robot_by_path_ties_to_the_lower():
    cost = np.ones((20, 30), np.float32)
    cost[:15, 15] = np.inf  # a wall with a gap at the bottom
    poses = [(2, 10), (2, 20), (2, 10)]
    labels = path_voronoi(cost, poses)
    distances = np.stack([shortest_path_tree(cost, pose)[0] for pose in poses])
    expected = np.argmin(distances, axis=0)
    expected[~np.isfinite(distances.min(axis=0))] = -1
    np.testing.assert_array_equal(labels, expected)
    assert labels[2, 14] == 0 and labels[2, 16] == 1 and labels[0, 15] == -1
    assert not (labels == 2).any()  # robot 2 stands on robot 0's cell: robot 0 has it


def test_the_partition_runs_over_predicted_free_cells_only():
    observed = np.full((3, 4), UNKNOWN, np.uint8)
    observed[:, 0] = FREE
    observed[0, 1] = OCCUPIED
    members = np.full((4, 3, 4), 0.5, np.float32)
    members[:, :, 2] = 0.1  # predicted free
    members[:, :, 3] = 0.9  # predicted wall
    cost = region_cost(observed, EnsemblePrediction(members), 0.5)
    assert np.isfinite(cost).tolist() == [[True, False, True, False]] * 3
    assert np.isfinite(region_cost(observed, None, 0.5)[1:]).all()


# ----------------------------------------------------------------------------- episodes


@pytest.mark.parametrize("name", ["mapex_assign", "mapex_voronoi"])
def test_a_team_of_one_is_the_single_robot_mapex_run(name, world, predictor):
    config = ExplorationConfig(steps=150, team=TeamConfig(assign_every_steps=10))
    team = run_episode(world, name, predictor, [2], robots=1, seed=3, config=config)
    alone = run_episode(world, "mapex", predictor, 2, seed=3, config=config)
    np.testing.assert_array_equal(team.trajectories[0], alone.trajectory)
    np.testing.assert_array_equal(team.final_observed, alone.final_observed)
    for curve in ("coverage", "iou", "tu"):
        np.testing.assert_array_equal(getattr(team.curves, curve), getattr(alone.curves, curve))
    assert team.is_team and team.robots == 1


def test_assign_every_k_steps_makes_every_robot_re_plan_in_step(world, predictor):
    config = ExplorationConfig(steps=60, team=TeamConfig(assign_every_steps=20))
    result = run_episode(world, "mapex_assign", predictor, [1], robots=2, seed=0, config=config)
    for stats in result.robot_stats:
        planned_at = {t for t, _, _ in stats.goals}
        assert {20, 40} <= planned_at


def test_a_waiting_robot_stands_still_and_looks_again_later(predictor):
    """Two robots, one room: in the corridor scene's world the second robot waits."""
    config = replace(CONFIG, steps=8, team=TeamConfig(idle_replan_steps=3))
    world = generate_floor_plan(5)
    result = run_episode(world, "mapex_voronoi", predictor, [1], robots=4, seed=0, config=config)
    stats = result.robot_stats
    for robot, path in enumerate(result.trajectories):
        still = np.flatnonzero((np.diff(path, axis=0) == 0).all(axis=1))
        if len(still):  # a robot that waited re-planned only every third step meanwhile
            assert stats[robot].replans <= 1 + len(path) // config.team.idle_replan_steps
