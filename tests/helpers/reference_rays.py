"""A slow, independent slab-method reference for ray traversal (`reference_walk`).

It shares no code with `mapex.raycast`: it computes every cell's interval of the ray
parameter t with the slab method and orders the cells the ray crosses for a positive length
by entry. The raycast, sensor and visibility tests check the kernels against it.
"""

from __future__ import annotations

import numpy as np


def _slab(lower_edges: np.ndarray, origin: float, d: float) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit t of the ray origin + t * d through each slab [edge, edge + 1)."""
    if d == 0.0:
        inside = (lower_edges <= origin) & (origin < lower_edges + 1)
        return np.where(inside, -np.inf, np.inf), np.where(inside, np.inf, -np.inf)
    inverse = 1.0 / d
    t_a = (lower_edges - origin) * inverse
    t_b = (lower_edges + 1 - origin) * inverse
    return np.minimum(t_a, t_b), np.maximum(t_a, t_b)


def reference_walk(
    shape: tuple[int, int], start: tuple[int, int], direction: tuple[float, float], range_cells
) -> np.ndarray:
    """int (n, 2): the cells the ray from `start`'s centre crosses, by entry, within range."""
    rows, cols = np.indices(shape)
    enter_row, exit_row = _slab(rows, start[0] + 0.5, direction[0])
    enter_col, exit_col = _slab(cols, start[1] + 0.5, direction[1])
    t_enter = np.maximum(np.maximum(enter_row, enter_col), 0.0)
    t_exit = np.minimum(exit_row, exit_col)
    crossed = (t_exit > t_enter) & (t_enter <= range_cells)
    order = np.argsort(t_enter[crossed], kind="stable")
    assert np.all(np.diff(t_enter[crossed][order]) > 0), "reference: two cells entered at once"
    return np.stack([rows[crossed], cols[crossed]], axis=1)[order]
