"""Frontier cells, clustering and frontier points (SPEC §3) on hand-made maps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from mapex.config import FrontierConfig
from mapex.frontiers import (
    extract_frontier_clusters,
    extract_frontiers,
    frontier_cells,
    frontier_clusters,
)
from mapex.grid import FREE, OCCUPIED, UNKNOWN


def _walled(shape: tuple[int, int]) -> np.ndarray:
    return np.full(shape, OCCUPIED, dtype=np.uint8)


def _strip(n_cells: int) -> np.ndarray:
    """A row of `n_cells` free cells under a row of unknown ones, walls elsewhere."""
    observed = _walled((4, n_cells + 4))
    observed[1, 2 : 2 + n_cells] = UNKNOWN
    observed[2, 2 : 2 + n_cells] = FREE
    return observed


def _reference_frontiers(observed: np.ndarray, min_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Slow, obvious implementation: label, then loop over clusters and cells."""
    unknown = np.pad(observed == UNKNOWN, 1, constant_values=False)
    near_unknown = ndimage.maximum_filter(unknown, size=3)[1:-1, 1:-1]
    frontier = (observed == FREE) & near_unknown
    labels, n = ndimage.label(frontier, structure=np.ones((3, 3)))
    points, sizes = [], []
    for label in range(1, n + 1):
        cells = np.argwhere(labels == label)
        if len(cells) < min_cells:
            continue
        dist2 = ((cells - cells.mean(axis=0)) ** 2).sum(axis=1)
        best = min(range(len(cells)), key=lambda i: (round(dist2[i], 9), *cells[i]))
        points.append(cells[best])
        sizes.append(len(cells))
    order = sorted(range(len(points)), key=lambda i: tuple(points[i]))
    return np.array([points[i] for i in order]).reshape(-1, 2), np.array([sizes[i] for i in order])


@pytest.mark.parametrize(("n_cells", "kept"), [(9, False), (10, False), (11, True), (12, True)])
def test_clusters_of_ten_or_fewer_cells_are_dropped(n_cells: int, kept: bool) -> None:
    points, sizes = extract_frontier_clusters(_strip(n_cells))
    assert len(points) == int(kept)
    if kept:
        assert sizes.tolist() == [n_cells]


@pytest.mark.parametrize(("n_cells", "expected_col"), [(11, 2 + 5), (12, 2 + 5), (13, 2 + 6)])
def test_point_of_a_straight_cluster_is_its_middle_cell_lowest_on_ties(
    n_cells: int, expected_col: int
) -> None:
    assert extract_frontiers(_strip(n_cells)).tolist() == [[2, expected_col]]


def _l_shape(arm_down: int, arm_right: int) -> np.ndarray:
    """Free L: column 2 from row 2 down `arm_down` cells, then right along the bottom row."""
    corner_row = 2 + arm_down - 1
    observed = _walled((corner_row + 4, 2 + arm_right + 4))
    observed[1 : corner_row + 2, 1] = UNKNOWN
    observed[corner_row + 1, 1 : 2 + arm_right + 1] = UNKNOWN
    observed[2 : corner_row + 1, 2] = FREE
    observed[corner_row, 2 : 2 + arm_right] = FREE
    return observed


def test_point_of_a_symmetric_l_is_the_closest_member_with_an_exact_tie_to_lowest_row() -> None:
    # 21 cells, mean (9.38, 4.62): (9, 2) and (12, 5) are exactly equally close.
    observed = _l_shape(arm_down=11, arm_right=11)
    points, sizes = extract_frontier_clusters(observed)
    assert sizes.tolist() == [21]
    assert points.tolist() == [[9, 2]]


def test_point_of_an_unequal_l_is_on_the_longer_arm() -> None:
    observed = _l_shape(arm_down=15, arm_right=8)
    points = extract_frontiers(observed)
    expected, _ = _reference_frontiers(observed, 11)
    assert points.tolist() == expected.tolist()
    assert points[0, 1] == 2  # on the vertical arm, not at the (empty) mean


def test_diagonal_only_contact_merges_two_clusters() -> None:
    observed = _walled((12, 16))
    observed[4, 1:7] = UNKNOWN
    observed[5, 1:7] = FREE  # six cells ending at (5, 6)
    observed[6, 7:13] = FREE  # six cells starting at (6, 7): diagonal contact only
    observed[7, 7:13] = UNKNOWN
    points, sizes = extract_frontier_clusters(observed)
    assert sizes.tolist() == [12]
    assert len(points) == 1


def test_cells_outside_the_map_are_not_unknown() -> None:
    observed = np.full((6, 20), FREE, dtype=np.uint8)
    assert not frontier_cells(observed).any()
    observed[:2] = UNKNOWN
    expected = np.zeros(observed.shape, dtype=bool)
    expected[2] = True  # includes the border cells (2, 0) and (2, 19)
    np.testing.assert_array_equal(frontier_cells(observed), expected)
    assert extract_frontiers(observed).tolist() == [[2, 9]]


def test_frontier_cells_are_free_with_an_unknown_eight_neighbour() -> None:
    observed = np.full((5, 5), FREE, dtype=np.uint8)
    observed[0, 0] = UNKNOWN
    observed[1, 1] = OCCUPIED
    expected = np.zeros((5, 5), dtype=bool)
    expected[0, 1] = expected[1, 0] = True  # (1, 1) touches it diagonally but is a wall
    np.testing.assert_array_equal(frontier_cells(observed), expected)


@pytest.mark.parametrize("code", [FREE, OCCUPIED, UNKNOWN])
def test_uniform_maps_have_no_frontiers(code: np.uint8) -> None:
    points, sizes = extract_frontier_clusters(np.full((30, 40), code, dtype=np.uint8))
    assert points.shape == (0, 2) and points.dtype == np.int32
    assert sizes.shape == (0,)


@pytest.mark.parametrize("seed", range(6))
def test_matches_a_slow_reference_on_random_maps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    blobs = ndimage.gaussian_filter(rng.standard_normal((70, 90)), 3)
    observed = np.where(blobs > 0.05, UNKNOWN, FREE).astype(np.uint8)
    observed[rng.random(observed.shape) < 0.08] = OCCUPIED
    points, sizes = extract_frontier_clusters(observed)
    expected_points, expected_sizes = _reference_frontiers(observed, 11)
    assert len(points) > 0
    assert points.dtype == np.int32
    np.testing.assert_array_equal(points, expected_points)
    np.testing.assert_array_equal(sizes, expected_sizes)


def test_points_are_sorted_by_row_then_column() -> None:
    rng = np.random.default_rng(7)
    observed = np.where(ndimage.gaussian_filter(rng.standard_normal((80, 80)), 2) > 0, 1, 0)
    points = extract_frontiers(observed.astype(np.uint8))
    assert len(points) > 3
    keys = [tuple(p) for p in points.tolist()]
    assert keys == sorted(keys)


def test_drop_size_comes_from_the_config() -> None:
    observed = _strip(5)
    assert len(extract_frontiers(observed)) == 0
    assert len(extract_frontiers(observed, FrontierConfig(max_dropped_cluster_cells=4))) == 1


@pytest.mark.parametrize(
    "bad", [np.zeros((4, 4), dtype=np.float32), np.zeros((2, 4, 4), dtype=np.uint8), [[0, 1]]]
)
def test_bad_input_is_rejected(bad: object) -> None:
    with pytest.raises(ValueError, match="2-D uint8"):
        extract_frontiers(bad)  # type: ignore[arg-type]


@pytest.mark.parametrize(("n_cells", "last_resort"), [(4, True), (10, True), (11, False)])
def test_dropped_clusters_open_on_a_side_are_the_last_resort_tier(n_cells, last_resort) -> None:
    clusters = frontier_clusters(_strip(n_cells), small=True)
    assert len(clusters) == int(last_resort)
    if last_resort:
        assert clusters.sizes.tolist() == [n_cells]
        assert len(clusters.members(0)) == n_cells


def test_the_unseen_diagonal_cell_of_a_wall_corner_is_no_last_resort() -> None:
    observed = _walled((8, 8))
    observed[1:7, 1:7] = FREE
    observed[0, 0] = UNKNOWN  # the corner cell no ray reaches: diagonal to free (1, 1) only
    assert frontier_cells(observed)[1, 1]
    assert len(frontier_clusters(observed, small=True)) == 0
    assert len(frontier_clusters(observed)) == 0
