"""How soon any team could reach a coverage level from its starts: the radius bound.

Brass et al. (T-RO 2011) bound k robots' exploration time below by max(2e/k, 2r): however
many robots, none sees a cell before it could have driven near it. Here, with the robots'
moves and the sensor's range: a cell known at step t lies on a ray of at most
`range_cells` from a robot cell (every cell before it on the ray free), and that robot is
at most `cells_per_step * t` 8-connected moves through free cells from its start. So a cell
whose free-space hop distance from every start exceeds `cells_per_step * t + range_cells +
1` is unknown at step t, and coverage L cannot come before the first t at which the cells
within that distance make up L of the valid space. Moves are relaxed (corners may be cut,
cells next to walls are allowed) so the bound holds whatever the planner's cost map; it
ignores that rays are blocked by walls, so it is optimistic (docs/algorithms.md#teams).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from mapex.grid import Cell

UNREACHED = np.iinfo(np.int32).max


@njit(cache=True)
def _hops(free, sources):  # pragma: no cover - numba
    rows, cols = free.shape
    hops = np.full((rows, cols), UNREACHED, dtype=np.int32)
    queue = np.empty(rows * cols, dtype=np.int64)
    tail = 0
    for k in range(sources.shape[0]):
        r, c = sources[k, 0], sources[k, 1]
        if hops[r, c] != 0:
            hops[r, c] = 0
            queue[tail] = r * cols + c
            tail += 1
    head = 0
    while head < tail:
        node = queue[head]
        head += 1
        r, c = node // cols, node % cols
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                nr, nc = r + dr, c + dc
                if nr < 0 or nr >= rows or nc < 0 or nc >= cols or hops[nr, nc] != UNREACHED:
                    continue
                if free[nr, nc]:
                    hops[nr, nc] = hops[r, c] + 1
                    queue[tail] = nr * cols + nc
                    tail += 1
    return hops


def sight_hops(occupancy: np.ndarray, starts: Sequence[Cell]) -> np.ndarray:
    """int32 map: 8-connected moves through free cells from the nearest start, + 1 for a wall
    cell next to such a free cell (a ray ends on it); UNREACHED where no start leads."""
    occupancy = np.asarray(occupancy, dtype=bool)
    sources = np.asarray(starts, dtype=np.int64).reshape(-1, 2)
    if len(sources) == 0:
        raise ValueError("the radius bound needs at least one start")
    hops = _hops(~occupancy, sources)
    padded = np.pad(hops, 1, constant_values=UNREACHED).astype(np.int64)
    rows, cols = occupancy.shape
    nearest = np.min(
        [
            padded[1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
            for dr in (-1, 0, 1)
            for dc in (-1, 0, 1)
        ],
        axis=0,
    )
    walls = occupancy & (nearest < UNREACHED)
    hops[walls] = (nearest[walls] + 1).astype(np.int32)
    return hops


def radius_bound_steps(
    occupancy: np.ndarray,
    valid_space: np.ndarray,
    starts: Sequence[Cell],
    levels: Sequence[float],
    range_cells: int,
    cells_per_step: int,
) -> dict[float, int | None]:
    """level -> the first step at which coverage (known valid cells / valid cells) could reach
    it from `starts`, however many robots (module doc); None: never (too few valid cells lie
    within sight of free space connected to a start)."""
    hops = sight_hops(occupancy, starts)[np.asarray(valid_space, dtype=bool)]
    total = hops.size
    if total == 0:
        raise ValueError("the radius bound needs a non-empty valid space")
    ordered = np.sort(hops[hops < UNREACHED])
    bounds: dict[float, int | None] = {}
    for level in levels:
        needed = int(np.ceil(level * total))  # cells known for coverage >= level
        if needed > len(ordered):
            bounds[level] = None
            continue
        farthest = int(ordered[max(needed, 1) - 1])  # hop distance of the needed-th nearest
        bounds[level] = max(0, -(-(farthest - range_cells - 1) // cells_per_step))
    return bounds
