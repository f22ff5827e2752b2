"""Coverage, IoU, topological understanding and AUC on hand-made maps (SPEC §6)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.metrics import (
    MetricsError,
    building_footprint,
    coverage,
    curve_auc,
    idle_steps,
    occupied_iou,
    predicted_occupancy,
    topological_understanding,
    tu_goals,
)
from mapex.search import path_from_tree, shortest_path_tree

REPO = Path(__file__).resolve().parents[2]


def two_rooms() -> tuple[np.ndarray, np.ndarray]:
    """Ground truth (True = wall) of two rooms joined by a door, and their valid space."""
    walls = np.zeros((12, 20), dtype=bool)
    walls[[0, -1], :] = True
    walls[:, [0, -1]] = True
    walls[:, 10] = True
    walls[9:11, 10] = False  # the door, near the bottom
    valid = ~walls
    valid[[0, -1], :] = valid[:, [0, -1]] = False
    return walls, valid


@pytest.mark.parametrize("code, expected", [(UNKNOWN, 0.0), (FREE, 1.0), (OCCUPIED, 1.0)])
def test_coverage_uniform_maps(code, expected):
    _, valid = two_rooms()
    assert coverage(np.full(valid.shape, code, dtype=np.uint8), valid) == expected


def test_coverage_counts_only_valid_space():
    valid = np.zeros((4, 4), dtype=bool)
    valid[:2, :2] = True
    observed = np.full((4, 4), FREE, dtype=np.uint8)
    observed[0, :2] = UNKNOWN  # half of the valid space is unknown
    observed[3, 3] = UNKNOWN  # outside: irrelevant
    assert coverage(observed, valid) == 0.5
    with pytest.raises(MetricsError):
        coverage(observed, np.zeros((4, 4), dtype=bool))


@pytest.mark.parametrize("margin, expected_cells", [(0, 1), (1, 5), (2, 13), (3, 29)])
def test_building_footprint_is_a_disc_dilation(margin, expected_cells):
    valid = np.zeros((11, 11), dtype=bool)
    valid[5, 5] = True
    footprint = building_footprint(valid, margin)
    assert footprint.dtype == bool and footprint.sum() == expected_cells
    rows, cols = np.nonzero(footprint)
    assert np.all((rows - 5) ** 2 + (cols - 5) ** 2 <= margin**2)


def test_building_footprint_contains_the_room_walls():
    walls, valid = two_rooms()
    footprint = building_footprint(valid, 3)
    assert footprint[walls].all()


def test_predicted_occupancy_keeps_known_cells_and_thresholds_unknown():
    observed = np.array([[FREE, OCCUPIED, UNKNOWN, UNKNOWN]], dtype=np.uint8)
    prediction = np.array([[0.9, 0.1, 0.5, 0.49]], dtype=np.float32)
    np.testing.assert_array_equal(
        predicted_occupancy(observed, prediction, 0.5), [[False, True, True, False]]
    )


def test_occupied_iou_values():
    truth = np.array([[1, 1, 0, 0, 1]], dtype=bool)
    predicted = np.array([[1, 0, 1, 0, 1]], dtype=bool)
    footprint = np.array([[1, 1, 1, 1, 0]], dtype=bool)  # the last cell is outside
    assert occupied_iou(truth, truth, footprint) == 1.0
    assert occupied_iou(predicted, truth, footprint) == pytest.approx(1 / 3)
    empty = np.zeros_like(truth)
    assert occupied_iou(empty, empty, footprint) == 1.0
    assert occupied_iou(empty, truth, footprint) == 0.0


def test_tu_goals_deterministic_and_in_free_valid_space():
    walls, valid = two_rooms()
    goals = tu_goals("two_rooms", walls, valid, (2, 2), 100)
    assert goals.shape == (100, 2)
    np.testing.assert_array_equal(goals, tu_goals("two_rooms", walls, valid, (2, 2), 100))
    assert valid[goals[:, 0], goals[:, 1]].all() and not walls[goals[:, 0], goals[:, 1]].any()
    assert len({tuple(g) for g in goals.tolist()}) == 100
    assert not np.array_equal(goals, tu_goals("two_rooms", walls, valid, (2, 3), 100))
    assert not np.array_equal(goals, tu_goals("other", walls, valid, (2, 2), 100))


def test_tu_goals_all_candidates_when_fewer_than_asked():
    walls, valid = two_rooms()
    goals = tu_goals("two_rooms", walls, valid, (2, 2), 10_000)
    assert len(goals) == int((valid & ~walls).sum())
    with pytest.raises(MetricsError):
        tu_goals("none", walls, np.zeros_like(valid), (2, 2), 5)


@pytest.mark.slow  # runs the command in a process of its own
def test_tu_goals_stable_across_processes():
    walls, valid = two_rooms()
    here = tu_goals("two_rooms", walls, valid, (2, 2), 5).tolist()
    script = (
        "import sys; sys.path.insert(0, 'tests/mapex')\n"
        "from test_metrics import two_rooms\n"
        "from mapex.metrics import tu_goals\n"
        "w, v = two_rooms()\n"
        "print(tu_goals('two_rooms', w, v, (2, 2), 5).tolist())\n"
    )
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(here)


def test_tu_is_one_when_prediction_equals_truth():
    walls, valid = two_rooms()
    goals = tu_goals("two_rooms", walls, valid, (2, 2), 100)
    assert topological_understanding(walls, walls, (2, 2), goals) == 1.0


def test_tu_drops_when_the_prediction_hides_a_wall():
    walls, valid = two_rooms()
    hidden = walls.copy()
    hidden[1:-1, 10] = False  # the predicted map misses the dividing wall
    goals = np.array([[2, 15], [3, 3], [2, 9]])  # across the wall, same room, same room
    assert topological_understanding(hidden, walls, (2, 2), goals) == pytest.approx(2 / 3)


def test_tu_fails_goals_unreachable_in_the_prediction():
    walls, valid = two_rooms()
    closed = walls.copy()
    closed[9:11, 10] = True  # the predicted map shuts the door
    goals = np.array([[2, 15], [3, 3], [6, 6], [10, 18]])
    assert topological_understanding(closed, walls, (2, 2), goals) == 0.5


@pytest.mark.parametrize("seed", range(10))
def test_tu_matches_per_goal_path_check(seed):
    rng = np.random.default_rng(seed)
    truth = rng.random((25, 40)) < 0.2
    predicted = truth & (rng.random(truth.shape) < 0.7)  # a prediction that misses walls
    predicted |= rng.random(truth.shape) < 0.05  # and invents a few
    start = (12, 20)
    goals = np.argwhere(~truth)[rng.choice(int((~truth).sum()), 60, replace=False)]
    cost = np.where(predicted, np.inf, 1.0).astype(np.float32)
    _, parent = shortest_path_tree(cost, start)
    successes = []
    for goal in map(tuple, goals.tolist()):
        path = path_from_tree(parent, goal, start)
        successes.append(path is not None and not truth[path[:, 0], path[:, 1]].any())
    tu = topological_understanding(predicted, truth, start, goals)
    assert tu == pytest.approx(np.mean(successes))


def test_idle_steps_count_the_steps_a_robot_stood_still():
    path = np.array([[0, 0], [0, 0], [0, 1], [0, 1], [0, 1], [1, 1], [1, 1]])
    assert idle_steps(path) == 4
    assert idle_steps(path[:1]) == 0  # no step taken
    assert idle_steps(np.array([[2, 3], [3, 2]])) == 0


def test_curve_auc_is_the_mean():
    assert curve_auc([0.0, 0.5, 1.0, 0.5]) == 0.5
    with pytest.raises(MetricsError):
        curve_auc([])
