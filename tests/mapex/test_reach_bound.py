"""The radius bound (`mapex.reach_bound`) on hand-made corridors, and against real runs: no
run reaches a level before its bound, and every cell a run knew lies within the bound's
sight distance of its starts."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mapex.config import ExplorationConfig
from mapex.episode import run_episode
from mapex.grid import UNKNOWN
from mapex.metrics import coverage
from mapex.prediction import make_predictor
from mapex.reach_bound import UNREACHED, radius_bound_steps, sight_hops
from mapex.worlds import generate_floor_plan


def corridor(length: int = 100) -> np.ndarray:
    """Occupancy of a one-cell corridor (row 1) between two walls (rows 0 and 2)."""
    occupancy = np.ones((3, length), dtype=bool)
    occupancy[1] = False
    return occupancy


def test_hops_count_moves_through_free_cells_and_one_more_onto_a_wall():
    hops = sight_hops(corridor(10), [(1, 0)])
    assert hops[1].tolist() == list(range(10))
    assert hops[0].tolist() == [1, *range(1, 10)]  # a wall: its nearest free neighbour + 1


def test_a_wall_closes_the_way():
    occupancy = corridor(10)
    occupancy[1, 5] = True
    hops = sight_hops(occupancy, [(1, 0)])
    assert hops[1, 5] == 5 and (hops[1, 6:] == UNREACHED).all()


@pytest.mark.parametrize(
    ("starts", "level", "expected"),
    [
        ([(1, 0)], 1.0, 30),  # farthest cell 99 hops: ceil((99 - 10 - 1) / 3)
        ([(1, 0)], 0.1, 0),  # 30 cells, all within sight of the start
        ([(1, 0)], 0.3, 6),  # 90 cells: the farthest 29 hops, ceil(18 / 3)
        ([(1, 0), (1, 99)], 1.0, 13),  # two ends: farthest 50 hops, ceil(39 / 3)
    ],
)
def test_corridor_bounds(starts, level, expected):
    valid = np.ones((3, 100), dtype=bool)
    bounds = radius_bound_steps(
        corridor(), valid, starts, [level], range_cells=10, cells_per_step=3
    )
    assert bounds == {level: expected}


def test_a_level_beyond_the_cells_in_reach_is_never():
    occupancy = corridor()
    occupancy[1, 50] = True  # the far half cannot be seen from the start
    valid = np.ones((3, 100), dtype=bool)
    bounds = radius_bound_steps(occupancy, valid, [(1, 0)], [0.4, 0.6], 10, 3)
    assert bounds[0.6] is None and bounds[0.4] is not None


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="start"):
        radius_bound_steps(corridor(), np.ones((3, 100), bool), [], [0.9], 10, 3)
    with pytest.raises(ValueError, match="valid space"):
        radius_bound_steps(corridor(), np.zeros((3, 100), bool), [(1, 0)], [0.9], 10, 3)


@pytest.mark.parametrize(("method", "robots"), [("nearest", 1), ("mapex_assign", 2)])
def test_no_run_gets_there_before_its_bound(method, robots):
    world = generate_floor_plan(2)
    metrics = replace(ExplorationConfig().metrics, reach_levels=(0.2, 0.4, 0.5))
    config = ExplorationConfig(steps=400, metrics=metrics)
    predictor = make_predictor("classical") if method == "mapex_assign" else None
    result = run_episode(world, method, predictor, [0] * robots, robots=robots, config=config)
    starts = [tuple(int(v) for v in t[0]) for t in (result.trajectories or [result.trajectory])]
    sensor, motion = config.sensor, config.motion
    hops = sight_hops(world.occupancy, starts)
    known = (result.final_observed != UNKNOWN) & world.valid_space
    assert hops[known].max() <= motion.cells_per_step * config.steps + sensor.range_cells + 1
    levels = sorted(result.curves.reached["coverage"])
    bounds = radius_bound_steps(
        world.occupancy, world.valid_space, starts, levels, sensor.range_cells,
        motion.cells_per_step,
    )  # fmt: skip
    reached = [(level, result.curves.reached["coverage"][level]) for level in levels]
    assert any(step is not None for _, step in reached)  # the check compares something
    for level, step in reached:
        if step is not None:
            assert bounds[level] is not None and bounds[level] <= step
    final = coverage(result.final_observed, world.valid_space)
    assert final == pytest.approx(result.curves.coverage[-1], abs=1e-9)
