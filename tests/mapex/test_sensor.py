"""LiDAR scans and their integration against the slab-method reference of test_raycast."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from reference_rays import reference_walk

from mapex.config import SensorConfig
from mapex.grid import FREE, OCCUPIED, UNKNOWN, new_observed_map
from mapex.raycast import ray_directions
from mapex.sensor import Scan, cast_scan, integrate_scan, scan_and_integrate

SMALL = SensorConfig(n_rays=97, range_cells=25)


def random_world(seed: int, wall_fraction: float = 0.2) -> np.ndarray:
    """A random bool wall map of 20-60 cells a side."""
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(20, 61)), int(rng.integers(20, 61)))
    return rng.random(shape) < wall_fraction


def free_poses(occupancy: np.ndarray, count: int, seed: int) -> list[tuple[int, int]]:
    free = np.argwhere(~occupancy)
    rng = np.random.default_rng(seed)
    return [tuple(int(v) for v in free[i]) for i in rng.choice(len(free), count, replace=False)]


def reference_rays(
    occupancy: np.ndarray, pose, config: SensorConfig
) -> list[tuple[np.ndarray, bool]]:
    """Per ray: the cells walked up to and including the first wall, and whether it hit one."""
    rays = []
    for direction in ray_directions(config.n_rays):
        cells = reference_walk(occupancy.shape, pose, direction, config.range_cells)
        walls = np.flatnonzero(occupancy[cells[:, 0], cells[:, 1]])
        rays.append((cells[: walls[0] + 1], True) if len(walls) else (cells, False))
    return rays


@pytest.mark.parametrize("seed", range(6))
def test_cast_scan_matches_reference(seed: int) -> None:
    occupancy = random_world(seed, wall_fraction=0.05 + 0.05 * seed)
    config = SensorConfig(n_rays=97 + seed, range_cells=10 + 8 * seed)
    for pose in free_poses(occupancy, 3, seed):
        scan = cast_scan(occupancy, pose, config)
        expected = reference_rays(occupancy, pose, config)
        assert scan.pose == pose
        np.testing.assert_array_equal(scan.n_cells, [len(cells) for cells, _ in expected])
        np.testing.assert_array_equal(scan.hit, [hit for _, hit in expected])


@pytest.mark.parametrize("seed", range(4))
def test_integration_marks_exactly_the_walked_cells(seed: int) -> None:
    occupancy = random_world(100 + seed)
    observed = new_observed_map(occupancy.shape)
    expected = np.full(occupancy.shape, UNKNOWN)
    for pose in free_poses(occupancy, 4, seed):
        integrate_scan(observed, cast_scan(occupancy, pose, SMALL), SMALL)
        for cells, hit in reference_rays(occupancy, pose, SMALL):
            walked = expected[cells[:, 0], cells[:, 1]]
            expected[cells[:, 0], cells[:, 1]] = np.where(walked == OCCUPIED, OCCUPIED, FREE)
            if hit:
                expected[cells[-1, 0], cells[-1, 1]] = OCCUPIED
        np.testing.assert_array_equal(observed, expected)
        assert not np.any(occupancy & (observed == FREE)), "a wall was marked free"
        assert np.all(occupancy[observed == OCCUPIED]), "a free cell was marked occupied"


@pytest.mark.parametrize("seed", range(3))
def test_seen_gets_exactly_the_cells_each_scan_walked(seed: int) -> None:
    """A team's per-robot record: `seen` holds the cells this robot's scans walked, though
    the map they were integrated into already knew some of them."""
    occupancy = random_world(200 + seed)
    shared = new_observed_map(occupancy.shape)
    first, second = free_poses(occupancy, 2, seed)
    integrate_scan(shared, cast_scan(occupancy, first, SMALL), SMALL)  # a teammate's scan
    seen = np.zeros(occupancy.shape, dtype=bool)
    integrate_scan(shared, cast_scan(occupancy, second, SMALL), SMALL, seen)
    alone = new_observed_map(occupancy.shape)
    integrate_scan(alone, cast_scan(occupancy, second, SMALL), SMALL)
    np.testing.assert_array_equal(seen, alone != UNKNOWN)
    with pytest.raises(ValueError, match="seen must be bool"):
        integrate_scan(shared, cast_scan(occupancy, second, SMALL), SMALL, seen[1:])


def test_hits_are_occupied_walls_and_stay_occupied() -> None:
    occupancy = random_world(7)
    observed = new_observed_map(occupancy.shape)
    ever_occupied = np.zeros(occupancy.shape, dtype=bool)
    for pose in free_poses(occupancy, 6, 7):
        scan = scan_and_integrate(occupancy, observed, pose, SMALL)
        for (cells, _), hit in zip(reference_rays(occupancy, pose, SMALL), scan.hit, strict=True):
            if hit:
                assert occupancy[tuple(cells[-1])]
                assert observed[tuple(cells[-1])] == OCCUPIED
        assert np.all(observed[ever_occupied] == OCCUPIED)
        ever_occupied |= observed == OCCUPIED
    assert ever_occupied.any()


def test_an_occupied_cell_is_never_turned_free() -> None:
    occupancy = np.zeros((21, 21), dtype=bool)
    observed = new_observed_map(occupancy.shape)
    observed[10, 14] = OCCUPIED  # on the east ray from (10, 10), free in the ground truth
    config = SensorConfig(n_rays=4, range_cells=30)
    scan = scan_and_integrate(occupancy, observed, (10, 10), config)
    assert scan.n_cells[0] == 11 and not scan.hit[0]  # walks on, to the border
    assert observed[10, 14] == OCCUPIED
    assert np.all(observed[10, 10:14] == FREE) and np.all(observed[10, 15:] == FREE)


@pytest.mark.parametrize("seed", range(4))
def test_scan_and_integrate_equals_cast_then_integrate(seed: int) -> None:
    occupancy = random_world(200 + seed)
    rng = np.random.default_rng(seed)
    start = rng.choice([FREE, UNKNOWN, OCCUPIED], size=occupancy.shape, p=[0.2, 0.7, 0.1])
    one_pass, two_pass = start.astype(np.uint8), start.astype(np.uint8)
    for pose in free_poses(occupancy, 3, seed):
        fast = scan_and_integrate(occupancy, one_pass, pose, SMALL)
        slow = cast_scan(occupancy, pose, SMALL)
        integrate_scan(two_pass, slow, SMALL)
        np.testing.assert_array_equal(fast.n_cells, slow.n_cells)
        np.testing.assert_array_equal(fast.hit, slow.hit)
        np.testing.assert_array_equal(one_pass, two_pass)


def test_axis_rays_in_a_walled_box() -> None:
    occupancy = np.zeros((12, 30), dtype=bool)
    occupancy[[0, -1], :] = True
    occupancy[:, [0, -1]] = True
    scan = cast_scan(occupancy, (4, 7), SensorConfig(n_rays=4, range_cells=100))
    # east, south, west, north: cells walked including the wall
    np.testing.assert_array_equal(scan.n_cells, [23, 8, 8, 5])
    assert scan.hit.all()


@pytest.mark.parametrize("pose", [(0, 0), (0, 17), (29, 39), (15, 0), (29, 20)])
def test_poses_next_to_the_border(pose) -> None:
    occupancy = random_world(9, wall_fraction=0.1)[:30, :40].copy()
    occupancy[pose] = False
    observed = new_observed_map(occupancy.shape)
    scan = scan_and_integrate(occupancy, observed, pose, SMALL)
    expected = reference_rays(occupancy, pose, SMALL)
    np.testing.assert_array_equal(scan.n_cells, [len(cells) for cells, _ in expected])
    np.testing.assert_array_equal(scan.hit, [hit for _, hit in expected])
    assert observed[pose] == FREE


def test_range_ends_rays_without_a_hit() -> None:
    occupancy = np.zeros((50, 50), dtype=bool)
    scan = cast_scan(occupancy, (25, 25), SensorConfig(n_rays=8, range_cells=10))
    assert not scan.hit.any()
    assert scan.n_cells[0] == 11  # the start cell and 10 more entered at t <= 10


@pytest.mark.parametrize("pose", [(-1, 3), (3, -1), (20, 3), (3, 20), (2.0, 3), ("a", 1), (1,)])
def test_bad_poses_are_rejected(pose) -> None:
    occupancy = np.zeros((20, 20), dtype=bool)
    with pytest.raises(ValueError, match="pose"):
        cast_scan(occupancy, pose, SMALL)
    with pytest.raises(ValueError, match="pose"):
        scan_and_integrate(occupancy, new_observed_map((20, 20)), pose, SMALL)


def test_pose_in_a_wall_is_rejected() -> None:
    occupancy = np.zeros((20, 20), dtype=bool)
    occupancy[5, 6] = True
    with pytest.raises(ValueError, match="in a wall"):
        cast_scan(occupancy, (5, 6), SMALL)


def test_bad_maps_are_rejected() -> None:
    occupancy = np.zeros((20, 20), dtype=bool)
    with pytest.raises(ValueError, match="bool"):
        cast_scan(occupancy.astype(np.uint8), (1, 1), SMALL)
    with pytest.raises(ValueError, match="observed"):
        scan_and_integrate(occupancy, new_observed_map((20, 21)), (1, 1), SMALL)
    with pytest.raises(ValueError, match="observed"):
        scan_and_integrate(occupancy, np.ones((20, 20), dtype=np.int64), (1, 1), SMALL)


def test_scans_that_do_not_fit_are_rejected() -> None:
    occupancy = np.zeros((20, 20), dtype=bool)
    scan = cast_scan(occupancy, (10, 10), SMALL)
    with pytest.raises(ValueError, match="rays"):
        integrate_scan(new_observed_map((20, 20)), scan, SensorConfig(n_rays=98, range_cells=25))
    too_long = Scan((10, 10), scan.n_cells + np.uint16(1), scan.hit.copy())
    with pytest.raises(ValueError, match="past the range"):
        integrate_scan(new_observed_map((20, 20)), too_long, SMALL)
    empty_ray = Scan((10, 10), np.zeros_like(scan.n_cells), scan.hit.copy())
    with pytest.raises(ValueError, match="start cell"):
        integrate_scan(new_observed_map((20, 20)), empty_ray, SMALL)


def test_scan_arrays_are_compact_and_read_only() -> None:
    scan = cast_scan(np.zeros((20, 20), dtype=bool), (3, 3), SMALL)
    assert scan.n_cells.dtype == np.uint16 and scan.hit.dtype == np.bool_
    assert scan.n_rays == SMALL.n_rays
    with pytest.raises(ValueError):
        scan.n_cells[0] = 3
    with pytest.raises(ValueError, match="1-D"):
        Scan((0, 0), np.zeros(3, dtype=np.uint16), np.zeros(4, dtype=bool))


def _kth_walls(map_dir: Path) -> np.ndarray:
    """SPEC §1 ground truth: walls of the 0.05 m map, 2x2 block-min (any wall) at 0.1 m."""
    walls = np.load(map_dir / "occ_map.npy") == 0
    walls = np.pad(walls, ((0, walls.shape[0] % 2), (0, walls.shape[1] % 2)), constant_values=True)
    return walls.reshape(walls.shape[0] // 2, 2, walls.shape[1] // 2, 2).any(axis=(1, 3))


def test_no_wall_is_ever_marked_free_on_a_kth_map(kth_dev_dir: Path) -> None:
    occupancy = _kth_walls(kth_dev_dir / "50015847")
    observed = new_observed_map(occupancy.shape)
    config = SensorConfig()
    for pose in free_poses(occupancy, 5, 0):
        scan_and_integrate(occupancy, observed, pose, config)
    assert (observed == OCCUPIED).sum() > 1000
    assert not np.any(occupancy & (observed == FREE))
    assert np.all(occupancy[observed == OCCUPIED])
