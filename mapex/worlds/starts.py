"""Start poses of the KTH protocol (SPEC §1): one near each corner of the valid space.

Each start is the cell nearest (Euclidean; ties broken by row, then column) to a corner of
the valid-space bounding box that is free, inside valid space and has at least
`clearance_cells` free cells between it and any wall: its distance-transform value
(cell centre to the nearest wall-cell centre) is at least `clearance_cells + 1`.
Cells beyond the map edge count as walls, since the robot cannot go there either.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from mapex.grid import Cell
from mapex.worlds.base import World, WorldError


def start_poses(world: World, clearance_cells: int) -> list[Cell]:
    """Four starts: nearest to the top-left, top-right, bottom-left, bottom-right corner.

    Two corners may share a start on a tiny map; WorldError when no cell qualifies.
    """
    if clearance_cells < 0:
        raise ValueError(f"clearance_cells must be >= 0, got {clearance_cells}")
    rows, cols = np.nonzero(eligible_start_cells(world, clearance_cells))
    if rows.size == 0:
        raise WorldError(
            f"world '{world.name}': no free valid cell with {clearance_cells} cells of clearance"
        )
    return [_nearest(rows, cols, corner) for corner in _valid_space_corners(world)]


def eligible_start_cells(world: World, clearance_cells: int) -> np.ndarray:
    """Bool map of the cells that are free, valid and `clearance_cells` clear of any wall."""
    free = ~world.occupancy
    walled = np.pad(free, 1, constant_values=False)  # the map edge is a wall
    wall_distance = ndimage.distance_transform_edt(walled)[1:-1, 1:-1]
    return free & world.valid_space & (wall_distance >= clearance_cells + 1)


def _valid_space_corners(world: World) -> list[Cell]:
    rows, cols = np.nonzero(world.valid_space)
    if rows.size == 0:
        raise WorldError(f"world '{world.name}': empty valid space")
    top, bottom = int(rows.min()), int(rows.max())
    left, right = int(cols.min()), int(cols.max())
    return [(top, left), (top, right), (bottom, left), (bottom, right)]


def _nearest(rows: np.ndarray, cols: np.ndarray, corner: Cell) -> Cell:
    """The candidate nearest to `corner`; candidates come in row-major order, so argmin's
    first minimum is the tie-break by row, then column."""
    squared = (rows - corner[0]) ** 2 + (cols - corner[1]) ** 2
    best = int(np.argmin(squared))
    return (int(rows[best]), int(cols[best]))
