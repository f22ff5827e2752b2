"""mapex_path and mapex_plus on hand-made scenes: path cost, the gain along the way, each cell
counted once, and their settings."""

import dataclasses

import numpy as np
import pytest

from mapex.config import ConfigError, ExplorationConfig, apply_overrides
from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.methods import PlanningContext, make_method
from mapex.methods.path_gain import (
    path_cells,
    path_viewpoints,
    per_path_cost,
    revealed_cell_worth,
)
from mapex.methods.paths import frontier_paths
from mapex.navigation import cost_map, reachable_mask
from mapex.prediction.base import EnsemblePrediction
from mapex.visibility import group_visibility_gain, visibility_gain, visible_mask

DISAGREEING = np.array([0.1, 0.6, 0.2, 0.5], dtype=np.float32)  # G, G_1..G_3 on unknown cells


def short_sight_config(**path_gain) -> ExplorationConfig:
    """Rays of 15 cells, so each frontier sees only the unknown space next to it."""
    config = ExplorationConfig()
    return dataclasses.replace(
        config,
        visibility=dataclasses.replace(config.visibility, range_cells=15),
        path_gain=dataclasses.replace(config.path_gain, **path_gain),
    )


def context_for(observed, robot, frontiers, config) -> PlanningContext:
    """The ensemble copies known cells and disagrees (same values everywhere) on unknown ones."""
    members = np.repeat((observed.astype(np.float32) / 2)[None], 4, axis=0)
    unknown = observed == UNKNOWN
    members[:, unknown] = DISAGREEING[:, None]
    cost = cost_map(observed, config.navigation)
    return PlanningContext(
        observed=observed,
        pose=np.array(robot),
        frontiers=np.array(frontiers, dtype=np.int64),
        prediction=EnsemblePrediction(members),
        cost=cost,
        reachable=reachable_mask(cost, robot),
        config=config,
        rng=np.random.default_rng(0),
    )


def walled_room(wall_to_the_left: bool) -> tuple[np.ndarray, tuple, list]:
    """A room (rows 10-50, cols 20-80) open to unknown space on both sides, robot in the
    middle; optionally a wall at col 35 that leaves a gap only at the bottom (rows 45-50)."""
    observed = np.full((61, 101), UNKNOWN, dtype=np.uint8)
    observed[10:51, 20:81] = FREE
    observed[9, 19:82] = OCCUPIED
    observed[51, 19:82] = OCCUPIED
    if wall_to_the_left:
        observed[10:45, 35] = OCCUPIED
    return observed, (30, 50), [[30, 20], [30, 80]]


@pytest.mark.parametrize("name", ["mapex_path", "mapex_plus"])
def test_a_frontier_behind_a_wall_loses_to_an_equal_one_in_open_line(name):
    config = short_sight_config()
    observed, robot, frontiers = walled_room(wall_to_the_left=True)
    context = context_for(observed, robot, frontiers, config)
    straight = make_method("mapex", config).score(context)
    assert straight[0] == pytest.approx(straight[1], rel=0.02)  # equally valuable and far
    scores = make_method(name, config).score(context)
    assert scores[1] > 1.3 * scores[0]  # the detour round the wall costs
    assert make_method(name, config).select_goal(context).cell[1] > robot[1]


def corridor(doors_on_the_left: bool) -> tuple[np.ndarray, tuple, list]:
    """A known corridor (rows 28-32, cols 5-95) between unknown space, robot in its middle,
    a frontier at each end; optionally three open doors into unknown rooms on the left half."""
    observed = np.full((61, 101), UNKNOWN, dtype=np.uint8)
    observed[28:33, 5:96] = FREE
    observed[27, 4:97] = OCCUPIED
    observed[33, 4:97] = OCCUPIED
    if doors_on_the_left:
        for col in (15, 25, 35):
            observed[27, col : col + 4] = FREE
    return observed, (30, 50), [[30, 5], [30, 95]]


def test_the_path_past_open_doors_gains_what_they_reveal():
    config = short_sight_config()
    observed, robot, frontiers = corridor(doors_on_the_left=True)
    context = context_for(observed, robot, frontiers, config)
    plus = make_method("mapex_plus", config)
    scores = plus.score(context)
    assert make_method("mapex_path", config).score(context)[0] == pytest.approx(
        make_method("mapex_path", config).score(context)[1], rel=0.02
    )  # the same gain at both ends
    assert scores[0] > 1.5 * scores[1]
    assert plus.select_goal(context).cell[1] < robot[1]
    closed, *_ = corridor(doors_on_the_left=False)
    without_doors = plus.score(context_for(closed, robot, frontiers, config))
    assert without_doors[0] == pytest.approx(without_doors[1], rel=0.02)
    assert scores[0] > 1.5 * without_doors[0]


def test_a_group_counts_each_visible_cell_once():
    rng = np.random.default_rng(3)
    opacity = (rng.random((50, 60)) < 0.08).astype(np.float32)
    ones = np.ones_like(opacity)
    a, b = (25, 20), (25, 35)
    args = (40, 30, "threshold", 0.5)
    union = visible_mask(opacity, a, *args) | visible_mask(opacity, b, *args)
    gains = group_visibility_gain(opacity, ones, [np.array([a, b]), np.array([a, a])], *args)
    single = visibility_gain(opacity, ones, np.array([a, b]), *args)
    assert gains[0] == union.sum()
    assert gains[1] == single[0]  # the same viewpoint twice counts its cells once
    assert max(single) <= gains[0] <= single.sum()


def test_groups_beyond_255_keep_their_own_stamps():
    opacity = np.zeros((20, 20), dtype=np.float32)
    weights = np.ones_like(opacity)
    groups = [np.array([[10, 10]])] * 600
    gains = group_visibility_gain(opacity, weights, groups, 36, 5, "threshold", 0.5)
    assert np.all(gains == gains[0]) and gains[0] > 0


@pytest.mark.parametrize("variance_weight", [0.0, 0.5, 1.0])
def test_gains_are_non_negative_and_unreachable_frontiers_rank_last(variance_weight):
    config = short_sight_config(variance_weight=variance_weight)
    observed, robot, frontiers = walled_room(wall_to_the_left=True)
    observed[40:51, 60:70] = OCCUPIED
    observed[44:47, 64:67] = FREE  # a pocket no path reaches
    context = context_for(observed, robot, [*frontiers, [45, 65]], config)
    worth = revealed_cell_worth(context, variance_weight)
    assert worth.min() >= 0 and np.all(worth[observed != UNKNOWN] == 0)
    for name in ("mapex_path", "mapex_plus"):
        scores = make_method(name, config).score(context)
        assert np.all(scores[:2] >= 0) and scores[2] == -np.inf


def test_path_viewpoints_sample_the_path_and_end_at_the_frontier():
    path = np.array([[0, c] for c in range(25)])
    views = path_viewpoints(path, np.array([0, 25]), every_cells=10)
    np.testing.assert_array_equal(views, [[0, 10], [0, 20], [0, 25]])


def test_frontier_paths_reach_an_inflated_frontier_from_its_neighbour():
    config = short_sight_config()
    observed, robot, _ = walled_room(wall_to_the_left=False)
    context = context_for(observed, robot, [[10, 50], [30, 80]], config)  # (10, 50): by a wall
    paths = frontier_paths(context)
    assert np.isfinite(paths.cost).all()
    path = paths.path(0)
    assert tuple(path[0]) == robot and tuple(path[-1]) == tuple(paths.entry[0])
    assert np.abs(paths.entry[0] - [10, 50]).max() <= 1


@pytest.mark.parametrize(
    "override, message",
    [
        ("path_gain.variance_weight=1.5", "variance_weight must be in"),
        ("path_gain.variance_weight=-0.1", "variance_weight must be in"),
        ("path_gain.path_sample_cells=0", "path_sample_cells must be >= 1"),
        ("path_gain.top_k=0", "top_k must be >= 1"),
        ("path_gain.cost_offset_cells=-1", "cost_offset_cells must be >= 0"),
        ("path_gain.cost_offset_cells=nan", "cost_offset_cells must be >= 0"),
        ("path_gain.replan_every_steps=-5", "replan_every_steps must be >= 0"),
    ],
)
def test_bad_settings_are_one_line_errors(override, message):
    with pytest.raises(ConfigError, match=message) as info:
        apply_overrides(ExplorationConfig(), [override])
    assert "\n" not in str(info.value)


def test_without_variance_every_unknown_cell_is_worth_one():
    config = short_sight_config(variance_weight=1.0)
    observed, robot, frontiers = corridor(doors_on_the_left=False)
    context = context_for(observed, robot, frontiers, config)
    agreeing = np.repeat(context.prediction.members[:1], 4, axis=0)
    context = dataclasses.replace(context, prediction=EnsemblePrediction(agreeing))
    worth = revealed_cell_worth(context, 1.0)
    np.testing.assert_array_equal(worth, (observed == UNKNOWN).astype(np.float32))


def test_cost_offset_lets_a_large_gain_further_away_win():
    gain, path_cost = np.array([1.0, 5.0]), np.array([2.0, 20.0])
    assert np.argmax(per_path_cost(gain, path_cost)) == 0
    assert np.argmax(per_path_cost(gain, path_cost, offset_cells=20.0)) == 1
    assert per_path_cost(gain, np.array([np.inf, 3.0]), offset_cells=20.0)[0] == -np.inf


@pytest.mark.parametrize("every, expected", [(0, None), (15, 15)])
def test_mapex_plus_replans_periodically_only_when_asked(every, expected):
    method = make_method("mapex_plus", short_sight_config(replan_every_steps=every))
    assert method.replan_every_steps == expected


def test_the_cells_measure_counts_moves_and_ignores_the_wall_penalty():
    observed, robot, frontiers = walled_room(wall_to_the_left=True)
    context = context_for(observed, robot, frontiers, short_sight_config())
    paths = frontier_paths(context)
    cells = path_cells(paths)
    for i in range(len(frontiers)):
        assert cells[i] == len(paths.path(i)) - 1
        assert cells[i] <= paths.cost[i]  # the planner charges walls' neighbourhoods more
    planner = make_method("mapex_plus", short_sight_config()).score(context)
    config = short_sight_config(cost_measure="cells")
    by_cells = make_method("mapex_plus", config).score(dataclasses.replace(context, config=config))
    assert by_cells[1] == planner[1]  # a straight path in the open: the same cost
    assert by_cells[0] > planner[0]  # around the wall: 39 moves, cost 54.5
    with pytest.raises(ConfigError, match="choose one of"):
        apply_overrides(ExplorationConfig(), ["path_gain.cost_measure=metres"])
