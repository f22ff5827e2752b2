"""World size limit: a world above `world.max_cells` is refused in one line that names the
limit and the `--set` that raises it."""

import numpy as np
import pytest

from mapex.config import ConfigError, ExplorationConfig, apply_overrides
from mapex.worlds.base import World, WorldError


def blank_world(rows: int, cols: int) -> World:
    return World("blank", np.zeros((rows, cols), dtype=bool), np.ones((rows, cols), dtype=bool))


def test_a_world_within_the_limit_passes():
    world = blank_world(20, 50)
    assert world.check_size(1000) is world


def test_a_world_above_the_limit_is_refused_with_the_way_to_raise_it():
    with pytest.raises(WorldError) as info:
        blank_world(20, 51).check_size(1000)
    message = str(info.value)
    assert "1,020 cells (20 x 51), above the limit of 1,000" in message
    assert "--set world.max_cells=1020" in message and "\n" not in message


def test_the_default_limit_takes_every_development_map_size():
    assert ExplorationConfig().world.max_cells >= 1157 * 1025  # IPA office_g, the largest


def test_a_limit_below_one_is_a_one_line_error():
    with pytest.raises(ConfigError, match="world.max_cells must be >= 1"):
        apply_overrides(ExplorationConfig(), ["world.max_cells=0"])
