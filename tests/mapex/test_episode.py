import numpy as np
import pytest

from mapex.config import ExplorationConfig
from mapex.episode import run_episode
from mapex.grid import FREE, OCCUPIED
from mapex.prediction import make_predictor
from mapex.worlds import generate_floor_plan
from mapex.worlds.base import World
from mapex.worlds.starts import eligible_start_cells


@pytest.fixture(scope="module")
def nearest_run():
    world = generate_floor_plan(3)
    result = run_episode(
        world, "nearest", make_predictor("classical"), 0, 0, ExplorationConfig(steps=200)
    )
    return world, result


def test_curves_are_sampled_on_schedule(nearest_run):
    _, result = nearest_run
    assert result.curves.steps == list(range(0, 201, 50))
    tu_sampled = [
        t for t, v in zip(result.curves.steps, result.curves.tu, strict=True) if np.isfinite(v)
    ]
    assert tu_sampled == [0, 100, 200]
    assert all(0.0 <= v <= 1.0 for v in result.curves.coverage + result.curves.iou)
    assert result.curves.coverage == sorted(result.curves.coverage)  # coverage never drops


def test_motion_obeys_the_model(nearest_run):
    world, result = nearest_run
    steps = np.abs(np.diff(result.trajectory, axis=0)).max(axis=1)
    assert steps.max() <= 3  # at most 3 cells (Chebyshev) per step
    assert not world.occupancy[result.trajectory[:, 0], result.trajectory[:, 1]].any()


def test_observed_map_agrees_with_ground_truth(nearest_run):
    world, result = nearest_run
    observed = result.final_observed
    assert not world.occupancy[observed == FREE].any()
    assert world.occupancy[observed == OCCUPIED].all()


def test_small_room_ends_early_and_holds_values():
    occupancy = np.ones((40, 40), dtype=bool)
    occupancy[5:35, 5:35] = False
    world = World("room", occupancy, ~occupancy)
    result = run_episode(world, "nearest", None, 0, 0, ExplorationConfig(steps=300))
    assert result.finished_at is not None and result.finished_at < 50
    assert result.end_reason == "explored"
    assert result.curves.steps == list(range(0, 301, 50))
    assert result.curves.coverage[-1] == pytest.approx(1.0)
    assert len(set(result.curves.coverage[1:])) == 1  # held from the end state on
    assert len(result.trajectory) == result.finished_at + 1


def test_a_run_that_uses_its_budget_ends_for_that_reason(nearest_run):
    _, result = nearest_run
    assert result.finished_at is None and result.end_reason == "budget"


def test_an_explicit_start_cell_is_where_the_robot_starts():
    world = generate_floor_plan(3)
    cell = tuple(int(v) for v in np.argwhere(eligible_start_cells(world, 3))[500])
    result = run_episode(world, "nearest", None, cell, 0, ExplorationConfig(steps=20))
    assert result.start == cell and result.start_index is None and result.start_spec == cell
    assert tuple(result.trajectory[0]) == cell


def test_prediction_method_needs_a_predictor():
    with pytest.raises(ValueError, match="needs a predictor"):
        run_episode(generate_floor_plan(0), "mapex", None, 0, 0, ExplorationConfig(steps=5))
