"""The traversal core against a slow, independent slab-method reference
(`reference_rays.reference_walk`, which shares no code with `mapex.raycast`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_rays import reference_walk

from mapex.raycast import ray_angles, ray_directions, trace_ray


def test_ray_angles_are_evenly_spaced_from_zero() -> None:
    angles = ray_angles(8)
    np.testing.assert_allclose(angles, np.arange(8) * np.pi / 4)
    assert angles.dtype == np.float64


@pytest.mark.parametrize("n_rays", [0, -3])
def test_ray_angles_reject_no_rays(n_rays: int) -> None:
    with pytest.raises(ValueError, match="n_rays"):
        ray_angles(n_rays)


def test_ray_directions_are_unit_sin_cos_and_read_only() -> None:
    directions = ray_directions(12)
    assert directions.shape == (12, 2)
    for k, (d_row, d_col) in enumerate(directions):
        assert d_row == pytest.approx(math.sin(2 * math.pi * k / 12), abs=1e-15)
        assert d_col == pytest.approx(math.cos(2 * math.pi * k / 12), abs=1e-15)
    assert not directions.flags.writeable


@pytest.mark.parametrize(
    ("direction", "expected_last"),
    [((0.0, 1.0), (5, 15)), ((0.0, -1.0), (5, 0)), ((1.0, 0.0), (15, 5)), ((-1.0, 0.0), (0, 5))],
)
def test_axis_rays_walk_range_plus_one_cells_or_to_the_border(direction, expected_last) -> None:
    cells = trace_ray(20, 40, 5, 5, direction[0], direction[1], 10)
    assert tuple(cells[0]) == (5, 5)
    assert tuple(cells[-1]) == expected_last
    steps = np.abs(np.diff(cells, axis=0)).sum(axis=1)
    assert np.all(steps == 1)


@pytest.mark.parametrize(("range_cells", "n_cells"), [(10.5, 12), (10.49, 11), (0, 1), (0.5, 2)])
def test_a_cell_entered_exactly_at_the_range_counts(range_cells: float, n_cells: int) -> None:
    cells = trace_ray(20, 40, 5, 5, 0.0, 1.0, range_cells)  # enters col 5 + j at t = j - 0.5
    assert len(cells) == n_cells


def test_ray_leaving_the_map_at_once_walks_only_its_start_cell() -> None:
    cells = trace_ray(10, 10, 0, 0, -1.0, 0.0, 50)
    np.testing.assert_array_equal(cells, [[0, 0]])


def test_exact_diagonal_steps_through_corners() -> None:
    s = math.sqrt(0.5)
    cells = trace_ray(30, 30, 2, 3, s, s, 100)
    np.testing.assert_array_equal(cells, [[2 + i, 3 + i] for i in range(27)])
    np.testing.assert_array_equal(cells, reference_walk((30, 30), (2, 3), (s, s), 100))


@pytest.mark.parametrize("n_rays", [4, 8, 97, 360])
def test_ray_fan_matches_reference(n_rays: int) -> None:
    rng = np.random.default_rng(n_rays)
    shape = (int(rng.integers(20, 60)), int(rng.integers(20, 60)))
    start = (int(rng.integers(shape[0])), int(rng.integers(shape[1])))
    for d_row, d_col in ray_directions(n_rays):
        cells = trace_ray(shape[0], shape[1], start[0], start[1], d_row, d_col, 25)
        np.testing.assert_array_equal(cells, reference_walk(shape, start, (d_row, d_col), 25))


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    n_rows=st.integers(1, 50),
    n_cols=st.integers(1, 50),
    start_fraction=st.tuples(st.floats(0, 0.999), st.floats(0, 0.999)),
    angle=st.floats(0, 2 * math.pi),
    range_cells=st.one_of(st.integers(0, 80), st.floats(0, 80)),
)
def test_random_rays_match_reference(n_rows, n_cols, start_fraction, angle, range_cells) -> None:
    start = (int(start_fraction[0] * n_rows), int(start_fraction[1] * n_cols))
    direction = (math.sin(angle), math.cos(angle))
    cells = trace_ray(n_rows, n_cols, start[0], start[1], direction[0], direction[1], range_cells)
    expected = reference_walk((n_rows, n_cols), start, direction, range_cells)
    np.testing.assert_array_equal(cells, expected)
    assert np.all(np.abs(np.diff(cells, axis=0)).max(axis=1) == 1)  # neighbours, in order
