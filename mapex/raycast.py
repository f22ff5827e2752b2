"""The one grid-traversal core shared by the LiDAR (`mapex.sensor`) and visibility raycasts.

Exact Amanatides-Woo traversal from the centre of the start cell, with boundary-crossing
distances computed directly, never accumulated, so a LiDAR scan, its retrace on the observed
map and a visibility ray walk the same cells; the geometry (angles, which cells count, cell
corners, range) is in docs/algorithms.md#sensor. Kernels call `ray_through` once per ray,
`start_state` once per walk and `next_cell` per step: small @njit functions that numba
inlines into the callers' loops. The walk state is a tuple (row, col, half_row, half_col);
a walk loop reads the cell as state[0], state[1].
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit


def ray_angles(n_rays: int) -> np.ndarray:
    """float64 (n_rays,): theta_k = 2 pi k / n_rays in radians, k = 0 .. n_rays - 1."""
    if n_rays < 1:
        raise ValueError(f"n_rays must be at least 1, got {n_rays}")
    return 2.0 * np.pi * np.arange(n_rays, dtype=np.float64) / n_rays


@lru_cache(maxsize=16)
def ray_directions(n_rays: int) -> np.ndarray:
    """Read-only float64 (n_rays, 2): unit (d_row, d_col) = (sin, cos) of `ray_angles`."""
    angles = ray_angles(n_rays)
    directions = np.stack([np.sin(angles), np.cos(angles)], axis=1)
    directions.flags.writeable = False
    return directions


@njit(cache=True)
def ray_through(d_row: float, d_col: float) -> tuple[int, int, float, float]:
    """The constants of a ray with direction (d_row, d_col): (step_row, step_col, inv_row, inv_col).

    step_* in {-1, 0, 1} is the sign of the direction component; inv_* = 1 / |d_*|
    (infinite for a zero component, so that axis is never crossed).
    """
    step_row = 1 if d_row > 0.0 else (-1 if d_row < 0.0 else 0)
    step_col = 1 if d_col > 0.0 else (-1 if d_col < 0.0 else 0)
    inv_row = 1.0 / abs(d_row) if d_row != 0.0 else np.inf
    inv_col = 1.0 / abs(d_col) if d_col != 0.0 else np.inf
    return (step_row, step_col, inv_row, inv_col)


@njit(cache=True)
def start_state(row: int, col: int) -> tuple[int, int, float, float]:
    """The walk state at the start cell: (row, col, half_row, half_col).

    half_* = crossings of that axis so far + 0.5: the next boundary of the axis lies
    half_* cells from the start along it, so the ray reaches it at t = half_* * inv_*.
    """
    return (row, col, 0.5, 0.5)


@njit(cache=True)
def next_cell(
    ray: tuple[int, int, float, float], state: tuple[int, int, float, float]
) -> tuple[tuple[int, int, float, float], float]:
    """The state at the cell after `state`'s cell and the distance t (cells) it is entered at."""
    step_row, step_col, inv_row, inv_col = ray
    row, col, half_row, half_col = state
    t_row = half_row * inv_row
    t_col = half_col * inv_col
    if t_row < t_col:
        return (row + step_row, col, half_row + 1.0, half_col), t_row
    if t_col < t_row:
        return (row, col + step_col, half_row, half_col + 1.0), t_col
    # exactly through a corner: step diagonally
    return (row + step_row, col + step_col, half_row + 1.0, half_col + 1.0), t_row


@njit(cache=True)
def inside(n_rows: int, n_cols: int, row: int, col: int) -> bool:
    """Whether (row, col) is a cell of an (n_rows, n_cols) map."""
    return 0 <= row < n_rows and 0 <= col < n_cols


@njit(cache=True)
def trace_ray(
    n_rows: int, n_cols: int, row0: int, col0: int, d_row: float, d_col: float, range_cells: float
) -> np.ndarray:
    """int64 (n, 2): every cell the ray walks on an empty map, in order (tests, plots)."""
    ray = ray_through(d_row, d_col)
    state = start_state(row0, col0)
    cells = np.empty((2 * int(range_cells) + 4, 2), dtype=np.int64)
    n = 0
    while True:
        cells[n, 0] = state[0]
        cells[n, 1] = state[1]
        n += 1
        state, t = next_cell(ray, state)
        if t > range_cells or not inside(n_rows, n_cols, state[0], state[1]):
            return cells[:n].copy()
