"""The cluster goal rule of SPEC §3 (mapex.methods.goals), on hand-made worlds.

Each choice is checked against a brute-force reading of the rule: every member (or every
reachable known-free cell) measured, the nearest one taken.
"""

import numpy as np
import pytest
from handmade_worlds import ROOM_CENTRE, grazing_door_world, slit_room_world

from mapex.config import ExplorationConfig, FrontierConfig
from mapex.episode import run_episode
from mapex.explorer import Explorer
from mapex.frontiers import frontier_clusters
from mapex.grid import FREE
from mapex.methods import METHODS, FrontierScorer, PlanningContext, make_method
from mapex.methods.goals import cluster_goal
from mapex.navigation import cost_map, reachable_mask
from mapex.prediction import make_predictor
from mapex.simulator import Simulator
from mapex.worlds import load_world

CONFIG = ExplorationConfig(steps=300)
FRONTIER_SCORERS = sorted(n for n, cls in METHODS.items() if issubclass(cls, FrontierScorer))


def first_scan_context(world, scanned_from=None) -> PlanningContext:
    """The planning context after the first scan from the room centre."""
    explorer = Explorer(world.shape, make_method("nearest", CONFIG), None, CONFIG, seed=0)
    explorer.observe(Simulator(world, [ROOM_CENTRE], CONFIG.sensor, CONFIG.motion).scan(0))
    cost = cost_map(explorer.observed, CONFIG.navigation)
    clusters = frontier_clusters(explorer.observed, CONFIG.frontier)
    return PlanningContext(
        observed=explorer.observed,
        pose=explorer.pose,
        frontiers=clusters.points,
        prediction=None,
        cost=cost,
        reachable=reachable_mask(cost, ROOM_CENTRE),
        config=CONFIG,
        rng=np.random.default_rng(0),
        clusters=clusters,
        scanned_from=explorer.scanned_from if scanned_from is None else scanned_from,
    )


def test_an_unreachable_point_gives_way_to_the_reachable_member_nearest_to_it():
    context = first_scan_context(grazing_door_world())
    assert len(context.frontiers) == 1  # the sliver through the door
    point = context.frontiers[0]
    assert not context.can_reach(point)
    goal = cluster_goal(context, 0)
    assert goal is not None and goal.approach
    members = context.cluster_members(0)
    reachable = [m for m in members if context.can_reach(m)]
    assert reachable, "the near end of the sliver is reachable"
    nearest = min(np.hypot(*(m - point)) for m in reachable)
    assert any((goal.cell == m).all() for m in reachable)
    assert np.hypot(*(goal.cell - point)) == pytest.approx(nearest)
    np.testing.assert_array_equal(goal.frontier, point)


def test_a_cluster_out_of_reach_is_approached_from_the_nearest_reachable_cell():
    context = first_scan_context(slit_room_world())
    assert len(context.frontiers) >= 1
    index = 0
    members = context.cluster_members(index)
    assert not any(context.can_reach(m) for m in members)
    goal = cluster_goal(context, index)
    assert goal is not None and goal.approach
    standing = np.argwhere(context.reachable & (context.observed == FREE))
    gaps = np.hypot(*(standing[:, None, :] - members[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert context.reachable[goal.cell[0], goal.cell[1]]
    assert gaps[(standing == goal.cell).all(axis=1)][0] == pytest.approx(gaps.min(), abs=1e-4)


def test_a_cell_already_scanned_from_is_never_a_goal():
    context = first_scan_context(slit_room_world())
    goal = cluster_goal(context, 0)
    scanned = context.scanned_from.copy()
    scanned[goal.cell[0], goal.cell[1]] = True
    assert cluster_goal(first_scan_context(slit_room_world(), scanned), 0) is None


class _Unscorable(FrontierScorer):
    """Scores nothing it can rank: every cluster must still be tried."""

    name = "unscorable"

    def score(self, context):
        return np.full(len(context.frontiers), -np.inf)


def test_clusters_the_method_cannot_score_are_still_tried():
    context = first_scan_context(grazing_door_world())
    assert _Unscorable(CONFIG).select_goal(context) is not None


@pytest.mark.parametrize("method", FRONTIER_SCORERS)
def test_the_grazing_door_room_explores_the_building(method):
    result = run_episode(
        grazing_door_world(), method, make_predictor("classical"), ROOM_CENTRE, 0, CONFIG
    )
    assert result.stats.approach_goals >= 1
    assert result.end_reason == "explored"
    assert result.curves.coverage[-1] == pytest.approx(1.0)


def test_a_room_sealed_for_the_robot_ends_unreachable_once_every_approach_is_scanned():
    world = slit_room_world()
    result = run_episode(world, "nearest", None, ROOM_CENTRE, 0, CONFIG)
    assert result.end_reason == "unreachable" and result.finished_at < 50
    assert result.stats.approach_goals >= 1
    visited = {tuple(cell) for cell in result.trajectory.tolist()}
    assert all((row, col) in visited for _, row, col in result.stats.goals)


def test_a_door_whose_frontier_is_a_small_cluster_is_still_explored():
    """A start in a room whose only door, seen obliquely, shows a frontier of 10 cells or
    fewer (generated:4, found by the stall audit): the size rule drops that cluster, the
    last-resort tier takes it."""
    world = load_world("generated:4")
    config = ExplorationConfig(steps=150)
    result = run_episode(world, "nearest", None, (97, 151), 0, config)
    assert result.end_reason == "budget" and result.curves.coverage[-1] > 0.1
    strict = ExplorationConfig(steps=150, frontier=FrontierConfig(small_clusters_last=False))
    dropped = run_episode(world, "nearest", None, (97, 151), 0, strict)
    assert dropped.end_reason == "explored" and dropped.finished_at == 0
