"""Procedural floor plans: deterministic, sealed, one connected building of many rooms, with
solid or free space outside."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from mapex.worlds import WorldError, generate_floor_plan, load_world
from mapex.worlds.__main__ import main
from mapex.worlds.config import OPEN_PLAN_CONFIG, ProceduralConfig
from mapex.worlds.procedural import (
    CORRIDOR_LABEL,
    FloorLayout,
    generate_layout,
    plan_config,
)

SEEDS = [0, 1, 3, 7, 11, 42]
EIGHT = np.ones((3, 3), dtype=bool)
CONFIG = ProceduralConfig()


@cache
def layout(seed: int) -> FloorLayout:
    return generate_layout(seed)


@pytest.mark.parametrize("seed", SEEDS)
def test_same_seed_gives_identical_plans(seed: int) -> None:
    first, second = layout(seed), generate_layout(seed)
    np.testing.assert_array_equal(first.world.occupancy, second.world.occupancy)
    np.testing.assert_array_equal(first.world.valid_space, second.world.valid_space)
    np.testing.assert_array_equal(first.labels, second.labels)
    assert first.world.name == second.world.name == f"generated:{seed}"


def test_different_seeds_give_different_plans() -> None:
    plans = [layout(seed).world for seed in SEEDS]
    for i, a in enumerate(plans):
        for b in plans[i + 1 :]:
            assert a.shape != b.shape or not np.array_equal(a.occupancy, b.occupancy)


@pytest.mark.parametrize("seed", SEEDS)
def test_size_is_in_range(seed: int) -> None:
    rows, cols = layout(seed).world.shape
    assert CONFIG.min_rows <= rows <= CONFIG.max_rows
    assert CONFIG.min_cols <= cols <= CONFIG.max_cols


@pytest.mark.parametrize("seed", SEEDS)
def test_border_is_sealed_with_wall(seed: int) -> None:
    walls = layout(seed).world.occupancy
    assert walls.dtype == bool
    assert walls[0].all() and walls[-1].all() and walls[:, 0].all() and walls[:, -1].all()


@pytest.mark.parametrize("seed", SEEDS)
def test_valid_space_is_the_free_space_and_one_8_connected_component(seed: int) -> None:
    world = layout(seed).world
    np.testing.assert_array_equal(world.valid_space, ~world.occupancy)
    _, count = ndimage.label(world.valid_space, structure=EIGHT)
    assert count == 1
    assert 0.5 < world.valid_space.mean() < 0.95  # a building, not a maze of walls


@pytest.mark.parametrize("seed", SEEDS)
def test_shutting_the_doors_splits_the_plan_into_its_rooms(seed: int) -> None:
    plan = layout(seed)
    shut = plan.world.occupancy | plan.doors
    components, count = ndimage.label(~shut, structure=EIGHT)
    labels = plan.labels[~shut]
    # every closed region holds exactly one space label, and every space is one region
    per_component = ndimage.labeled_comprehension(
        plan.labels, components, np.arange(1, count + 1), lambda v: len(np.unique(v)), int, 0
    )
    assert (per_component == 1).all()
    assert count == len(np.unique(labels))
    rooms = count - 1  # all corridors and open areas form one region
    assert rooms >= 6
    assert (labels == CORRIDOR_LABEL).any()


@pytest.mark.parametrize("seed", SEEDS)
def test_doors_are_wide_enough_to_pass_and_sit_in_thin_walls(seed: int) -> None:
    plan = layout(seed)
    openings, count = ndimage.label(plan.doors, structure=EIGHT)
    assert count >= 6
    for box in ndimage.find_objects(openings):
        across, along = sorted(s.stop - s.start for s in box)
        assert across <= CONFIG.wall_thickness_max
        assert along >= CONFIG.door_width_min


@pytest.mark.parametrize("seed", SEEDS)
def test_interior_walls_are_thin(seed: int) -> None:
    plan = layout(seed)
    walls = plan.world.occupancy
    inside = walls & (plan.labels > 0)  # walls of the building, not the solid outside
    assert inside.any()
    distance_to_free = ndimage.distance_transform_edt(walls)
    assert distance_to_free[inside].max() <= CONFIG.wall_thickness_max


def test_custom_config_bounds_the_size() -> None:
    config = ProceduralConfig(max_rows=200, max_cols=320)
    world = generate_floor_plan(5, config)
    assert world.shape[0] <= 200 and world.shape[1] <= 320


@pytest.mark.parametrize("seed", [-1, 2.5, "3"])
def test_bad_seed_is_rejected(seed) -> None:
    with pytest.raises(WorldError, match="bad generated seed"):
        generate_floor_plan(seed)


@pytest.mark.parametrize("flags", [[], ["--free-outside"]])
def test_demo_writes_a_png(tmp_path: Path, flags: list[str]) -> None:
    out = tmp_path / "plan.png"
    main(["--seed", "3", "--out", str(out), *flags])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@cache
def open_layout(seed: int) -> FloorLayout:
    return generate_layout(seed, plan_config(free_outside=True))


@pytest.mark.parametrize("seed", SEEDS)
def test_a_free_outside_plan_is_the_same_building_with_free_space_around_it(seed: int) -> None:
    walled, open_plan = layout(seed), open_layout(seed)
    world = open_plan.world
    assert world.name == f"generated-open:{seed}" == load_world(f"generated-open:{seed}").name
    np.testing.assert_array_equal(open_plan.labels, walled.labels)  # the same rooms
    inside = walled.labels > 0
    outside_free = ~world.occupancy & ~inside
    assert outside_free.sum() > 0.5 * (~inside).sum()  # mostly free; the outer walls remain
    np.testing.assert_array_equal(world.valid_space, inside & ~world.occupancy)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_free_outside_plan_is_still_sealed(seed: int) -> None:
    world = open_layout(seed).world
    components, _ = ndimage.label(~world.occupancy, structure=EIGHT)
    building = np.unique(components[world.valid_space])
    assert len(building) == 1  # one connected building, which no free cell outside reaches
    assert not np.isin(components[~world.occupancy & ~world.valid_space], building).any()


def wall_runs(plan: FloorLayout) -> tuple[np.ndarray, np.ndarray]:
    """Lengths of the runs of wall cells along rows and columns that have free cells at
    both ends: between two rooms (interior), and between a room and the outside (outline)."""
    walls, labels = plan.world.occupancy, plan.labels
    interior, outline = [], []
    for wall_lines, label_lines in ((walls, labels), (walls.T, labels.T)):
        for line, line_labels in zip(wall_lines, label_lines, strict=True):
            change = np.diff(line.astype(np.int8))
            starts, stops = np.flatnonzero(change == 1) + 1, np.flatnonzero(change == -1) + 1
            for start in starts:  # wall from `start` with a free cell before it
                later = stops[stops > start]
                if not len(later):
                    continue  # runs into the map's border
                stop = later[0]  # the first free cell after it
                ends = line_labels[start - 1], line_labels[stop]
                (outline if 0 in ends else interior).append(stop - start)
    return np.array(interior), np.array(outline)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_free_outside_plan_has_the_walls_of_the_kth_training_maps(seed: int) -> None:
    interior, outline = wall_runs(open_layout(seed))
    thickness = np.bincount(interior).argmax()  # one thickness per plan
    low, high = OPEN_PLAN_CONFIG.wall_thickness_min, OPEN_PLAN_CONFIG.wall_thickness_max
    assert low <= thickness <= high
    assert np.mean(interior == thickness) > 0.9  # the rest run along a wall's end
    assert np.mean(outline == OPEN_PLAN_CONFIG.outer_wall_thickness) > 0.9


@pytest.mark.parametrize("seed", SEEDS)
def test_a_sealed_plan_has_one_wall_thickness(seed: int) -> None:
    interior, _ = wall_runs(layout(seed))
    thickness = np.bincount(interior).argmax()
    assert CONFIG.wall_thickness_min <= thickness <= CONFIG.wall_thickness_max
    assert np.mean(interior == thickness) > 0.9
