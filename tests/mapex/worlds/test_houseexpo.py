"""HouseExpo plans: loading (one-line errors), the 0.1 m rasterisation rule on hand-made
polygons, single-house and corridor worlds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from mapex.worlds import WorldError, load_world
from mapex.worlds.config import HouseExpoConfig
from mapex.worlds.data import HOUSEEXPO_PLANS
from mapex.worlds.houseexpo import (
    HousePlans,
    corridor_world,
    house_world,
    load_plans,
    rasterise_plan,
)

# A 2 m x 1 m house from (0.1, 0.1) m with a 12 cm interior wall (a notch of the ring)
# rising 0.7 m from the bottom wall at x = 1.00-1.12 m: cm coordinates.
NOTCHED_HOUSE_CM = [
    (10, 10),
    (100, 10),
    (100, 80),
    (112, 80),
    (112, 10),
    (210, 10),
    (210, 110),
    (10, 110),
]


def _metres(points_cm) -> np.ndarray:
    return np.asarray(points_cm, np.float32) / 100


def _plans(rings_cm: list) -> HousePlans:
    rings = [_metres(ring) for ring in rings_cm]
    offsets = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
    ids = np.array([f"{i:032x}" for i in range(len(rings))])
    return HousePlans(ids, offsets, np.concatenate(rings))


def _brute_force_raster(points_cm, rows: int, cols: int) -> np.ndarray:
    """Free iff every 1 cm sub-cell centre of the 10 cm cell is inside (even-odd, PNPOLY)."""
    ring = np.asarray(points_cm, float)
    free = np.zeros((rows, cols), bool)
    for r in range(rows):
        for c in range(cols):
            free[r, c] = all(
                _inside(ring, 10 * c + j + 0.5, 10 * r + i + 0.5)
                for i in range(10)
                for j in range(10)
            )
    return free


def _inside(ring: np.ndarray, x: float, y: float) -> bool:
    inside = False
    for (ax, ay), (bx, by) in zip(ring, np.roll(ring, -1, axis=0), strict=True):
        if (ay > y) != (by > y) and x < ax + (y - ay) * (bx - ax) / (by - ay):
            inside = not inside
    return inside


def test_a_rectangle_with_a_notch_rasterises_to_cells_wholly_inside():
    free = rasterise_plan(_metres(NOTCHED_HOUSE_CM))
    assert free.shape == (12, 22)  # ceil(1.1 m / 0.1 m) + 1 rows, ceil(2.1 / 0.1) + 1 columns
    expected = np.zeros((12, 22), bool)
    expected[1:11, 1:21] = True
    expected[1:8, 10:12] = False  # the 12 cm wall covers parts of columns 10 and 11, rows 1-7
    np.testing.assert_array_equal(free, expected)


def test_an_oblique_ring_matches_the_brute_force_rule():
    ring = [(10, 10), (150, 10), (150, 60), (95, 117), (10, 117)]  # a slanted wall, odd sizes
    free = rasterise_plan(_metres(ring))
    np.testing.assert_array_equal(free, _brute_force_raster(ring, *free.shape))


def test_the_plan_is_sealed_by_wall_on_every_border():
    free = rasterise_plan(_metres(NOTCHED_HOUSE_CM))
    assert not (free[0].any() or free[-1].any() or free[:, 0].any() or free[:, -1].any())


def test_a_house_world_is_walls_around_its_free_space():
    world = house_world(0, _plans([NOTCHED_HOUSE_CM]))
    assert world.name == "houseexpo:0"
    np.testing.assert_array_equal(world.valid_space, ~world.occupancy)


def test_a_missing_plan_index_is_a_one_line_error():
    with pytest.raises(WorldError, match=r"no HouseExpo plan 3: there are 1 \(0-0\)"):
        house_world(3, _plans([NOTCHED_HOUSE_CM]))


def _write_npz(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p / "absent.npz", "missing HouseExpo plans file"),
        (lambda p: (p / "junk.npz").write_bytes(b"not a zip") and p / "junk.npz", "not a loadable"),
        (lambda p: _write_npz(p / "keys.npz", ids=np.array(["a"])), "no offsets, verts array"),
        (
            lambda p: _write_npz(
                p / "offsets.npz",
                ids=np.array(["a"]),
                offsets=np.array([0, 2]),
                verts=np.zeros((2, 2), np.float32),
            ),
            "rings of 3 or more vertices",
        ),
        (
            lambda p: _write_npz(
                p / "shape.npz", ids=np.array(["a"]), offsets=np.array([0, 3]), verts=np.zeros(6)
            ),
            "verts of shape (6,)",
        ),
    ],
)
def test_bad_plan_files_are_one_line_errors(tmp_path, make, message):
    path = make(tmp_path)
    with pytest.raises(WorldError) as error:
        load_plans(path)
    assert message in str(error.value) and "\n" not in str(error.value)


def _wide_house(width_cm: int, depth_cm: int) -> list[tuple[int, int]]:
    """A rectangle split in two rooms by a wall with a 1 m door (all free space connected)."""
    mid = 10 + width_cm // 2
    return [
        (10, 10), (mid, 10), (mid, 10 + depth_cm - 120), (mid + 12, 10 + depth_cm - 120),
        (mid + 12, 10), (10 + width_cm, 10), (10 + width_cm, 10 + depth_cm), (10, 10 + depth_cm),
    ]  # fmt: skip


HAND_MADE = _plans([_wide_house(600, 500), _wide_house(800, 450), _wide_house(500, 700)])
SMALL_WORLD = HouseExpoConfig(houses_per_world=4, min_house_side_cells=20)


def test_a_corridor_world_joins_every_house_to_one_valid_region():
    world = corridor_world(7, SMALL_WORLD, HAND_MADE)
    labels, count = ndimage.label(~world.occupancy)
    assert count == 1  # every house has its door to the corridor
    np.testing.assert_array_equal(world.valid_space, ~world.occupancy)
    corridor_rows = np.flatnonzero(
        world.valid_space.all(axis=1) | (world.valid_space.mean(axis=1) > 0.9)
    )
    assert len(corridor_rows) >= SMALL_WORLD.corridor_width_cells


def test_corridor_worlds_are_seeded():
    first, again = (corridor_world(3, SMALL_WORLD, HAND_MADE) for _ in range(2))
    np.testing.assert_array_equal(first.occupancy, again.occupancy)
    other = corridor_world(4, SMALL_WORLD, HAND_MADE)
    assert other.shape != first.shape or not np.array_equal(other.occupancy, first.occupancy)


def test_a_world_with_no_house_that_fits_is_a_one_line_error():
    config = HouseExpoConfig(min_house_side_cells=5, max_house_side_cells=10, max_draws=5)
    with pytest.raises(WorldError, match="could not draw 6 HouseExpo houses in 5 draws"):
        corridor_world(0, config, HAND_MADE)


@pytest.mark.parametrize("spec", ["houseexpo:x", "houseexpo-corridor:-1"])
def test_bad_houseexpo_specs_are_one_line_errors(spec):
    with pytest.raises(WorldError, match="expected a non-negative integer"):
        load_world(spec)


@pytest.mark.skipif(not HOUSEEXPO_PLANS.is_file(), reason="../shared/data/houseexpo is not present")
def test_the_shared_plans_load_as_houses_and_corridor_worlds():
    plans = load_plans()
    assert len(plans) > 30000
    house = load_world("houseexpo:0")
    corridor = load_world("houseexpo-corridor:0")
    assert house.valid_space.any() and corridor.valid_space.sum() > 4 * house.valid_space.sum() / 2
    assert ndimage.label(corridor.valid_space)[1] == 1
