"""Frontier visibility raycasts of docs/algorithms.md#methods: which cells a viewpoint would
see, and their gain.

One kernel over an `opacity` map (float32, rows x cols) serves every method that raycasts,
with the "threshold" or the "accumulate" stop rule; rays walk the cells of `mapex.raycast`,
like the LiDAR, up to `range_cells` or the map border, and the stopping cell is visible. A
viewpoint's gain is the sum of `weights` over its visible set, each cell once (callers give
already-known cells weight 0); a group of viewpoints (the samples of a path and its end,
`group_visibility_gain`) sees the union of their sets, each cell once.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mapex.raycast import inside, next_cell, ray_directions, ray_through, start_state

STOP_RULES = ("threshold", "accumulate")


def visibility_gain(
    opacity: np.ndarray,
    weights: np.ndarray,
    viewpoints: np.ndarray,
    n_rays: int,
    range_cells: int,
    stop_rule: str,
    epsilon: float,
) -> np.ndarray:
    """float64 (N,): sum of `weights` over the cells visible from each viewpoint.

    opacity, weights: float32 (rows, cols) (other dtypes are converted, at a copy's cost).
    viewpoints: int (N, 2) cells (row, col) inside the map.
    """
    opacity, weights = _checked_maps(opacity, weights)
    cells = _checked_viewpoints(viewpoints, opacity.shape)
    accumulate = _checked_ray_settings(n_rays, range_cells, stop_rule, epsilon)
    stamp = np.zeros(opacity.shape, dtype=np.uint8)
    groups = np.arange(len(cells), dtype=np.int64)
    return _run(opacity, weights, cells, groups, n_rays, range_cells, accumulate, epsilon, stamp)


def group_visibility_gain(
    opacity: np.ndarray,
    weights: np.ndarray,
    viewpoint_groups: list[np.ndarray],
    n_rays: int,
    range_cells: int,
    stop_rule: str,
    epsilon: float,
) -> np.ndarray:
    """float64 (G,): sum of `weights` over the union of the visible sets of each group of
    viewpoints (a cell seen from several viewpoints of a group counts once).

    viewpoint_groups: G int (n_g, 2) arrays of cells inside the map (an empty group gains 0),
    e.g. the samples of a path and its end; other arguments as `visibility_gain`.
    """
    opacity, weights = _checked_maps(opacity, weights)
    accumulate = _checked_ray_settings(n_rays, range_cells, stop_rule, epsilon)
    sizes = [len(group) for group in viewpoint_groups]
    arrays = [np.reshape(group, (-1, 2)) for group in viewpoint_groups]
    joined = np.concatenate(arrays) if arrays else np.zeros((0, 2), dtype=np.int64)
    cells = _checked_viewpoints(joined, opacity.shape)
    groups = np.repeat(np.arange(len(sizes), dtype=np.int64), sizes)
    stamp = np.zeros(opacity.shape, dtype=np.uint8)
    gains = _run(opacity, weights, cells, groups, n_rays, range_cells, accumulate, epsilon, stamp)
    return np.bincount(groups, weights=gains, minlength=len(sizes)).astype(np.float64)


def visible_mask(
    opacity: np.ndarray,
    viewpoint: tuple[int, int],
    n_rays: int,
    range_cells: int,
    stop_rule: str,
    epsilon: float,
) -> np.ndarray:
    """bool (rows, cols): the cells visible from one viewpoint (row, col) (plots, tests)."""
    opacity = _as_float32_map(opacity, "opacity")
    cells = _checked_viewpoints(np.asarray([viewpoint]), opacity.shape)
    accumulate = _checked_ray_settings(n_rays, range_cells, stop_rule, epsilon)
    stamp = np.zeros(opacity.shape, dtype=np.uint8)
    no_weights = np.zeros(opacity.shape, dtype=np.float32)
    groups = np.zeros(1, dtype=np.int64)
    _run(opacity, no_weights, cells, groups, n_rays, range_cells, accumulate, epsilon, stamp)
    return stamp == 1


def _checked_maps(opacity: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both maps as float32 2-D arrays of one shape (ValueError otherwise)."""
    opacity = _as_float32_map(opacity, "opacity")
    weights = _as_float32_map(weights, "weights")
    if weights.shape != opacity.shape:
        raise ValueError(f"weights {weights.shape} and opacity {opacity.shape} differ in shape")
    return opacity, weights


def _as_float32_map(values: np.ndarray, name: str) -> np.ndarray:
    values = np.ascontiguousarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise ValueError(f"{name} must be a 2-D map, got shape {values.shape}")
    return values


def _checked_viewpoints(viewpoints: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """int64 (N, 2) copy of `viewpoints`, checked to be integer cells inside the map."""
    viewpoints = np.asarray(viewpoints)
    if viewpoints.ndim != 2 or viewpoints.shape[1] != 2 or viewpoints.dtype.kind not in "iu":
        raise ValueError(
            f"viewpoints must be an int (N, 2) array, got {viewpoints.dtype} {viewpoints.shape}"
        )
    cells = viewpoints.astype(np.int64)
    outside = (cells < 0).any(axis=1) | (cells >= np.asarray(shape)).any(axis=1)
    if outside.any():
        raise ValueError(f"viewpoint {tuple(cells[outside][0])} is outside the {shape} map")
    return cells


def _checked_ray_settings(n_rays: int, range_cells: int, stop_rule: str, epsilon: float) -> bool:
    """Validate the ray settings; return whether the stop rule is 'accumulate'."""
    if stop_rule not in STOP_RULES:
        raise ValueError(f"stop_rule must be one of {STOP_RULES}, got {stop_rule!r}")
    if n_rays < 1 or range_cells < 0:
        raise ValueError(f"need n_rays >= 1 and range_cells >= 0, got {n_rays}, {range_cells}")
    if not epsilon > 0.0:
        raise ValueError(f"epsilon must be positive, got {epsilon}")
    return stop_rule == "accumulate"


def _run(
    opacity, weights, cells, groups, n_rays, range_cells, accumulate, epsilon, stamp
) -> np.ndarray:
    """Call the kernel with fixed argument types (one compiled version)."""
    directions = ray_directions(n_rays)
    return _gain_kernel(
        opacity,
        weights,
        cells,
        groups,
        directions,
        float(range_cells),
        accumulate,
        float(epsilon),
        stamp,
    )


@njit(cache=True)
def _gain_kernel(
    opacity, weights, viewpoints, groups, directions, range_cells, accumulate, epsilon, stamp
):
    """Gain per viewpoint, each cell counted once per group. The viewpoints of a group are
    consecutive (`groups`: int64 group id per viewpoint); the g-th group met stamps its visible
    cells with g % 255 + 1 in the uint8 `stamp` (all zeros on entry), which is cleared again
    after every 255 groups."""
    gains = np.zeros(viewpoints.shape[0], dtype=np.float64)
    mark = 0
    for i in range(viewpoints.shape[0]):
        if i == 0 or groups[i] != groups[i - 1]:
            mark = mark % 255 + 1
            if mark == 1 and i > 0:
                stamp[:] = 0
        for k in range(directions.shape[0]):
            ray = ray_through(directions[k, 0], directions[k, 1])
            state = start_state(viewpoints[i, 0], viewpoints[i, 1])
            gains[i] += _walk_visible(
                opacity, weights, stamp, mark, ray, state, range_cells, accumulate, epsilon
            )
    return gains


@njit(cache=True)
def _walk_visible(opacity, weights, stamp, mark, ray, state, range_cells, accumulate, epsilon):
    """Walk one ray, stamping with `mark`; return the weight of the cells it stamps first."""
    n_rows, n_cols = opacity.shape
    delta = 0.0
    gain = 0.0
    while True:
        row, col = state[0], state[1]
        if stamp[row, col] != mark:
            stamp[row, col] = mark
            gain += weights[row, col]
        if accumulate:
            delta += opacity[row, col]
        else:
            delta = opacity[row, col]
        if delta >= epsilon:
            return gain
        state, t = next_cell(ray, state)
        if t > range_cells or not inside(n_rows, n_cols, state[0], state[1]):
            return gain
