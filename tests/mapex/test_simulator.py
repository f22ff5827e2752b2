import numpy as np
import pytest

from mapex.config import MotionConfig, SensorConfig
from mapex.simulator import MotionError, Simulator
from mapex.worlds.base import World


def corridor_world() -> World:
    occupancy = np.ones((9, 30), dtype=bool)
    occupancy[2:7, 1:29] = False
    return World("corridor", occupancy, ~occupancy)


def test_step_moves_and_scans():
    sim = Simulator(corridor_world(), [(4, 3)], SensorConfig(n_rays=360), MotionConfig())
    scan = sim.step(0, np.array([[4, 4], [4, 5], [5, 6]]))
    assert tuple(scan.pose) == (5, 6)
    assert tuple(sim.poses[0]) == (5, 6)


@pytest.mark.parametrize(
    "cells",
    [
        [[4, 4], [4, 5], [4, 6], [4, 7]],  # too many cells in one step
        [[4, 5]],  # a jump of two cells
        [[3, 3], [2, 3], [1, 3]],  # into the wall
        [[4, 3]],  # not a move
    ],
)
def test_invalid_motion_is_rejected(cells):
    sim = Simulator(corridor_world(), [(4, 3)], SensorConfig(n_rays=360), MotionConfig())
    with pytest.raises(MotionError):
        sim.step(0, np.array(cells))
    assert tuple(sim.poses[0]) == (4, 3)
