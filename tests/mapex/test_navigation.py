"""Planning cost map, path planning and path following."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from mapex.config import NavigationConfig
from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.navigation import (
    NavigationError,
    advance_along_path,
    cost_map,
    path_is_clear,
    plan_path,
    unknown_within,
)

CONFIG = NavigationConfig()


def room(rows: int = 20, cols: int = 30) -> np.ndarray:
    """A fully known room: free inside, a one-cell occupied border."""
    observed = np.full((rows, cols), FREE, dtype=np.uint8)
    observed[[0, -1], :] = OCCUPIED
    observed[:, [0, -1]] = OCCUPIED
    return observed


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("inflation", [0, 1, 2])
def test_cost_map_matches_its_definition(seed, inflation):
    rng = np.random.default_rng(seed)
    observed = rng.choice([FREE, UNKNOWN, OCCUPIED], p=[0.8, 0.1, 0.1], size=(25, 31))
    observed = observed.astype(np.uint8)
    config = NavigationConfig(wall_inflation_cells=inflation)
    cost = cost_map(observed, config)
    assert cost.dtype == np.float32 and cost.shape == observed.shape

    walls = observed == OCCUPIED
    near_wall = np.zeros_like(walls)
    for r, c in np.argwhere(walls):
        near_wall[
            max(r - inflation, 0) : r + inflation + 1, max(c - inflation, 0) : c + inflation + 1
        ] = True
    passable = (observed == FREE) & ~near_wall
    np.testing.assert_array_equal(np.isfinite(cost), passable)

    distance = distance_transform_edt(~walls)
    clearance = config.wall_clearance_cells
    expected = 1 + config.wall_cost_weight * np.maximum(0, clearance - distance) / clearance
    np.testing.assert_allclose(cost[passable], expected[passable], rtol=1e-5)


def test_cost_map_decreases_away_from_a_wall():
    observed = np.full((9, 20), FREE, dtype=np.uint8)
    observed[:, 0] = OCCUPIED
    observed[0, 15:] = UNKNOWN  # unknown cells are no walls: they do not raise the cost
    cost = cost_map(observed, CONFIG)
    row = cost[4]
    assert np.all(np.isinf(row[:2]))  # the wall and its inflation
    far = int(CONFIG.wall_clearance_cells) + 1
    assert np.all(np.diff(row[1:far]) < 0)
    np.testing.assert_array_equal(row[far:], 1.0)
    assert np.isinf(cost[0, 15:]).all() and np.all(cost[1, 15:] == 1.0)


def test_cost_map_without_walls_is_unit_on_free_and_inf_on_unknown():
    observed = np.full((6, 6), FREE, dtype=np.uint8)
    observed[:, 3:] = UNKNOWN
    cost = cost_map(observed, CONFIG)
    np.testing.assert_array_equal(cost[:, :3], 1.0)
    assert np.isinf(cost[:, 3:]).all()


def test_cost_map_rejects_non_uint8_maps():
    with pytest.raises(NavigationError):
        cost_map(np.zeros((4, 4), dtype=np.int64), CONFIG)


def test_plan_path_stays_on_free_cells_and_reaches_a_goal_by_a_wall():
    observed = room()
    observed[10, 1:20] = OCCUPIED  # an inner wall with a gap at its end
    cost = cost_map(observed, CONFIG)
    start, goal = (5, 5), (11, 10)  # the goal touches the wall: inside the inflation
    assert np.isinf(cost[goal])
    path = plan_path(observed, cost, start, goal)
    assert path is not None and tuple(path[0]) == start and tuple(path[-1]) == goal
    assert np.all(observed[path[:, 0], path[:, 1]] == FREE)
    assert np.all(np.isfinite(cost[path[1:-1, 0], path[1:-1, 1]]))
    assert np.all(np.abs(np.diff(path, axis=0)).max(axis=1) == 1)


@pytest.mark.parametrize("goal_code", [UNKNOWN, OCCUPIED])
def test_plan_path_refuses_goals_that_are_not_known_free(goal_code):
    observed = room()
    observed[8, 8] = goal_code
    assert plan_path(observed, cost_map(observed, CONFIG), (5, 5), (8, 8)) is None


def test_plan_path_none_when_unreachable_or_outside():
    observed = room()
    observed[10, :] = OCCUPIED
    cost = cost_map(observed, CONFIG)
    assert plan_path(observed, cost, (5, 5), (15, 5)) is None
    assert plan_path(observed, cost, (5, 5), (50, 5)) is None


def test_path_is_clear_until_a_new_wall_inflates_it():
    observed = room()
    cost = cost_map(observed, CONFIG)
    path = plan_path(observed, cost, (10, 3), (10, 26))
    assert path_is_clear(observed, path, CONFIG)
    middle = path[len(path) // 2]
    observed[middle[0] + 1, middle[1]] = OCCUPIED  # a wall next to the path (seen later)
    assert not path_is_clear(observed, path, CONFIG)


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("inflation", [0, 1, 2])
def test_path_is_clear_on_the_observed_map_agrees_with_the_cost_map(seed, inflation):
    rng = np.random.default_rng(seed)
    observed = room()
    config = NavigationConfig(wall_inflation_cells=inflation)
    path = plan_path(observed, cost_map(observed, config), (10, 3), (10, 26))
    observed[rng.integers(0, 20, 6), rng.integers(0, 30, 6)] = OCCUPIED  # walls seen later
    observed[rng.integers(0, 20, 4), rng.integers(0, 30, 4)] = UNKNOWN
    inner = path[1:-1]
    expected = bool(np.isfinite(cost_map(observed, config)[inner[:, 0], inner[:, 1]]).all())
    assert path_is_clear(observed, path, config) is expected


def test_path_is_clear_ignores_robot_cell_and_goal():
    observed = np.full((3, 6), FREE, dtype=np.uint8)
    observed[2, [0, 5]] = OCCUPIED  # robot cell and goal sit next to walls
    path = np.array([[1, 0], [0, 1], [0, 2], [0, 3], [0, 4], [1, 5]])
    config = NavigationConfig(wall_inflation_cells=1)
    assert path_is_clear(observed, path, config)
    observed[1, 3] = OCCUPIED
    assert not path_is_clear(observed, path, config)


@pytest.mark.parametrize("cells_per_step, moved", [(0, 0), (1, 1), (3, 3), (4, 4), (9, 4)])
def test_advance_along_path(cells_per_step, moved):
    path = np.array([[0, 0], [1, 1], [2, 1], [3, 2], [3, 3]], dtype=np.int32)
    steps, remaining = advance_along_path(path, cells_per_step)
    np.testing.assert_array_equal(steps, path[1 : moved + 1])
    np.testing.assert_array_equal(remaining, path[moved:])
    assert steps.shape == (moved, 2)


@pytest.mark.parametrize("path, step", [(np.zeros((0, 2)), 3), (np.zeros((3, 2)), -1)])
def test_advance_along_path_rejects_bad_input(path, step):
    with pytest.raises(NavigationError):
        advance_along_path(path, step)


@pytest.mark.parametrize(
    "unknown_cell, radius, expected",
    [
        ((5, 15), 10.0, True),  # exactly on the circle
        ((11, 13), 10.0, True),  # 6^2 + 8^2 = 100
        ((12, 13), 10.0, False),  # 7^2 + 8^2 > 100
        ((13, 13), 10.0, False),  # inside the square window, outside the disc
        ((5, 5), 0.0, True),  # the cell itself
        ((5, 6), 0.5, False),
    ],
)
def test_unknown_within_is_a_euclidean_disc(unknown_cell, radius, expected):
    observed = np.full((30, 30), FREE, dtype=np.uint8)
    observed[unknown_cell] = UNKNOWN
    assert unknown_within(observed, (5, 5), radius) is expected


def test_unknown_within_at_the_map_edge():
    observed = np.full((4, 4), FREE, dtype=np.uint8)
    assert not unknown_within(observed, (0, 0), 10.0)
    observed[3, 3] = UNKNOWN
    assert unknown_within(observed, (0, 0), 10.0)
