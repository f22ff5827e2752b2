"""Start poses: nearest cell to each valid-space corner with enough wall clearance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

import mapex.worlds.starts as starts_module
from mapex.config import WorldConfig
from mapex.worlds import World, WorldError, generate_floor_plan, load_kth_map, start_poses
from mapex.worlds.starts import (
    eligible_start_cells,
    main_free_space,
    parse_start,
    start_argument,
    start_cell,
    start_cells,
    start_label,
    start_spec_of,
)

CLEARANCE = WorldConfig().start_clearance_cells
DEV_MAPS = ["50015847", "50015848", "50037764_PLAN1", "50052748"]


def room_world(rows: int = 20, cols: int = 30) -> World:
    """A walled rectangle whose whole interior is valid."""
    walls = np.zeros((rows, cols), dtype=bool)
    walls[[0, -1], :] = True
    walls[:, [0, -1]] = True
    return World("room", walls, ~walls)


def test_starts_of_a_rectangular_room_are_its_clear_corners() -> None:
    # clearance 3: a start needs 3 free cells to the wall, i.e. distance >= 4 from row/col 0
    assert start_poses(room_world(), 3) == [(4, 4), (4, 25), (15, 4), (15, 25)]


@pytest.mark.parametrize("clearance, first", [(0, (1, 1)), (1, (2, 2)), (5, (6, 6))])
def test_clearance_moves_the_start_away_from_the_walls(clearance: int, first) -> None:
    assert start_poses(room_world(), clearance)[0] == first


def test_ties_break_by_row_then_column() -> None:
    walls = np.ones((3, 3), dtype=bool)
    walls[0, 1] = walls[1, 0] = False  # both at distance 1 from the corner (0, 0)
    walls[1, 1] = False  # joins them (4-connected)
    world = World("tie", walls, np.ones((3, 3), dtype=bool))
    assert start_poses(world, 0)[0] == (0, 1)


def test_map_edge_counts_as_wall() -> None:
    world = World("open", np.zeros((10, 10), dtype=bool), np.ones((10, 10), dtype=bool))
    eligible = eligible_start_cells(world, 3)
    rows, cols = np.nonzero(eligible)
    assert rows.min() == 3 and rows.max() == 6 and cols.min() == 3 and cols.max() == 6


def test_starts_stay_in_valid_space() -> None:
    world = room_world()
    valid = np.zeros(world.shape, dtype=bool)
    valid[8:14, 10:20] = True
    world = World("part", world.occupancy, valid)
    starts = start_poses(world, 3)
    assert starts == [(8, 10), (8, 19), (13, 10), (13, 19)]


def test_no_clear_cell_is_an_error() -> None:
    with pytest.raises(WorldError, match="no free valid cell with 9 cells of clearance"):
        start_poses(room_world(), 9)


def test_negative_clearance_is_rejected() -> None:
    with pytest.raises(ValueError, match="clearance_cells"):
        start_poses(room_world(), -1)


def assert_good_starts(world: World, clearance: int) -> None:
    starts = start_poses(world, clearance)
    assert len(starts) == 4 and len(set(starts)) == 4
    walls = cKDTree(np.argwhere(world.occupancy))
    for row, col in starts:
        assert not world.occupancy[row, col] and world.valid_space[row, col]
        distance, _ = walls.query((row, col))
        assert distance >= clearance + 1
    assert start_poses(world, clearance) == starts  # deterministic
    # each start lies in its own corner's quadrant of the valid-space box
    rows, cols = np.nonzero(world.valid_space)
    mid_row, mid_col = (rows.min() + rows.max()) / 2, (cols.min() + cols.max()) / 2
    quadrants = [(r > mid_row, c > mid_col) for r, c in starts]
    assert quadrants == [(False, False), (False, True), (True, False), (True, True)]


@pytest.mark.parametrize("map_id", DEV_MAPS)
def test_dev_map_starts(kth_dev_dir: Path, map_id: str) -> None:
    assert_good_starts(load_kth_map(kth_dev_dir / map_id), CLEARANCE)


@pytest.mark.parametrize("seed", [0, 3, 8, 21])
def test_generated_world_starts(seed: int) -> None:
    assert_good_starts(generate_floor_plan(seed), CLEARANCE)


@pytest.mark.parametrize(
    ("text", "start", "argument", "label"),
    [("2", 2, "2", "start2"), ("15,380", (15, 380), "15,380", "start-r15c380"),
     (" 7 , 9 ", (7, 9), "7,9", "start-r7c9")],
)  # fmt: skip
def test_a_start_is_a_corner_or_a_cell(text, start, argument, label) -> None:
    assert parse_start(text) == start
    assert start_argument(start) == argument and parse_start(argument) == start
    assert start_label(start) == label


@pytest.mark.parametrize(
    ("text", "message"),
    [("4", "corners are 0-3"), ("-1", "expected a corner"), ("1,2,3", "expected a corner"),
     ("a,b", "expected a corner"), ("", "expected a corner")],
)  # fmt: skip
def test_a_bad_start_text_is_refused_in_one_line(text, message) -> None:
    with pytest.raises(ValueError, match=message):
        parse_start(text)


def test_an_explicit_cell_is_checked_against_the_world() -> None:
    walls = np.zeros((20, 30), dtype=bool)
    walls[[0, -1], :] = True
    walls[:, [0, -1]] = True
    valid = ~walls
    valid[:, 20:] = False  # a free strip outside the valid space
    world = World("room", walls, valid)
    assert start_cell(world, (10, 10), CLEARANCE) == (10, 10)
    assert start_cell(world, 0, CLEARANCE) == start_poses(world, CLEARANCE)[0]
    for cell, message in [
        ((20, 5), r"start cell \(20, 5\) is outside the map \(20 x 30 cells\)"),
        ((0, 5), r"start cell \(0, 5\) is on a wall"),
        ((10, 25), r"start cell \(10, 25\) is outside the valid space"),
        ((2, 10), r"start cell \(2, 10\) has less than 3 cells of clearance"),
    ]:
        with pytest.raises(WorldError, match=r"world 'room': " + message):
            start_cell(world, cell, CLEARANCE)


def test_a_cell_is_named_by_its_corner_when_it_is_one() -> None:
    world = room_world()
    corners = start_poses(world, CLEARANCE)
    assert start_spec_of(world, corners[2], CLEARANCE) == 2
    assert start_spec_of(world, (10, 10), CLEARANCE) == (10, 10)


def building_with_closet() -> World:
    """A 60 x 80 building with a closed 12 x 12 closet in its top-left corner (no door)."""
    walls = np.zeros((60, 80), dtype=bool)
    walls[[0, -1], :] = True
    walls[:, [0, -1]] = True
    walls[13, :14] = True  # the closet: rows 1-12, cols 1-12
    walls[:14, 13] = True
    return World("closet", walls, ~walls)


def test_a_corner_start_is_not_in_a_closed_closet() -> None:
    world = building_with_closet()
    starts = start_poses(world, CLEARANCE)
    in_closet = [row <= 12 and col <= 12 for row, col in starts]
    assert in_closet == [False, False, False, False]
    # the nearest cell to the top-left corner outside the closet: past its walls
    assert starts[0] == (4, 17) and starts[1:] == [(4, 75), (55, 4), (55, 75)]
    assert not eligible_start_cells(world, CLEARANCE)[:13, :13].any()


def test_an_explicit_cell_in_a_closed_closet_is_refused_in_one_line() -> None:
    world = building_with_closet()
    with pytest.raises(WorldError) as caught:
        start_cell(world, (6, 6), CLEARANCE)
    message = str(caught.value)
    assert "\n" not in message
    assert message == (
        "world 'closet': start cell (6, 6) is not connected to the largest free space of the "
        "world (a closed room?)"
    )
    assert start_cell(world, (30, 40), CLEARANCE) == (30, 40)


def test_free_space_outside_the_valid_space_connects_rooms() -> None:
    # two rooms joined by a doorway that is not valid space (as in the KTH maps): the small
    # room's corner stays there, it is connected to the large one
    walls = np.zeros((30, 80), dtype=bool)
    walls[[0, -1], :] = True
    walls[:, [0, -1, 20]] = True
    walls[12:18, 20] = False  # the doorway
    valid = ~walls
    valid[:, 20] = False
    world = World("doorway", walls, valid)
    assert main_free_space(world)[5, 5] and start_poses(world, CLEARANCE)[0] == (4, 4)


def test_the_largest_part_of_the_building_wins_over_larger_free_space_outside() -> None:
    # a sealed building inside a larger free area outside the valid space (generated-open)
    walls = np.zeros((100, 100), dtype=bool)
    walls[40:61, 40:61] = True
    walls[41:60, 41:60] = False
    valid = np.zeros_like(walls)
    valid[41:60, 41:60] = True
    world = World("open", walls, valid)
    assert main_free_space(world)[50, 50] and not main_free_space(world)[5, 5]
    assert start_poses(world, CLEARANCE)[0] == (44, 44)


def test_no_free_valid_cell_means_no_main_free_space() -> None:
    world = World("solid", np.ones((5, 5), dtype=bool), np.ones((5, 5), dtype=bool))
    assert not main_free_space(world).any()


def test_many_starts_are_judged_at_once_as_each_is_alone() -> None:
    """`start_cells` (issue #64, item 7): every cell of a building with a closet, a strip
    outside the valid space and cells off the map, in one call, is judged as `start_cell`'s
    rules judge it alone: the eligible ones are kept, and the first refused one is named."""
    world = building_with_closet()
    valid = world.valid_space.copy()
    valid[40:, 60:] = False
    world = World("closet", world.occupancy, valid)
    eligible = eligible_start_cells(world, CLEARANCE)
    good = [tuple(int(v) for v in cell) for cell in np.argwhere(eligible)]
    assert start_cells(world, [3, *good, 0], CLEARANCE) == [
        start_poses(world, CLEARANCE)[3],
        *good,
        start_poses(world, CLEARANCE)[0],
    ]
    every = [(r, c) for r in range(-1, 61) for c in range(-1, 81)]
    refused = [cell for cell in every if not (0 <= cell[0] < 60 and 0 <= cell[1] < 80)]
    refused += [tuple(int(v) for v in cell) for cell in np.argwhere(~eligible)]
    for cell in refused:
        with pytest.raises(WorldError) as alone:
            start_cell(world, cell, CLEARANCE)
        with pytest.raises(WorldError) as together:
            start_cells(world, [*good[:50], 1, cell, *refused], CLEARANCE)
        assert str(together.value) == str(alone.value)
    with pytest.raises(WorldError, match="start 7 is not a corner 0-3"):
        start_cells(world, [*good, 7, (0, 0)], CLEARANCE)
    with pytest.raises(WorldError, match=r"start cell \(1000000000000000000000, 5\) is outside"):
        start_cells(world, [(10**21, 5)], CLEARANCE)


def test_the_maps_starts_are_judged_on_are_computed_once_for_any_number(monkeypatch) -> None:
    """A thousand starts cost the map computations of one (it was one main free space and
    one eligible map per start: 61 ms each, 200 k starts > 300 s; issue #64, item 7)."""
    world = building_with_closet()
    cells = [tuple(int(v) for v in cell) for cell in np.argwhere(eligible_start_cells(world, 3))]
    calls = []
    real = starts_module.main_free_space
    monkeypatch.setattr(starts_module, "main_free_space", lambda w: calls.append(1) or real(w))
    counts = []
    for starts in ([cells[0]], cells[:1000], [0, *cells[:1000], 2, 3]):
        calls.clear()
        start_cells(world, starts, CLEARANCE)
        counts.append(len(calls))
    assert counts == [1, 1, 1]
