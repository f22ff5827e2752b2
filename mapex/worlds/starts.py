"""Start poses: one near each corner of the valid space (docs/algorithms.md#worlds), or an
explicit cell.

A start is named either by a corner index 0-3 (the project's protocol) or by a cell
(row, col) on the 0.1 m grid (the start poses a published protocol lists). On the command
line: `2` or `15,380`; in run names: `start2` or `start-r15c380`. A corner start is the
eligible start cell nearest to that corner of the valid-space bounding box; an eligible
cell is free, in the valid space, `clearance_cells` clear of walls and in the main free
space (the drivable space holding the most valid cells), and an explicit cell must be one.
The exact rules: docs/algorithms.md#worlds.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from mapex.config import NavigationConfig, WorldConfig, argparse_type
from mapex.grid import Cell
from mapex.worlds.base import World, WorldError

# the planner's default: a start must be where A* can drive to the rest of the building
ROBOT_WALL_INFLATION_CELLS = NavigationConfig().wall_inflation_cells

N_CORNERS = 4
StartSpec = int | tuple[int, int]
"""A corner index 0-3 or an explicit cell (row, col)."""


def parse_start(text: str) -> StartSpec:
    """`'0'`..`'3'` -> a corner index; `'ROW,COL'` -> a cell. ValueError (one line) otherwise."""
    parts = [part.strip() for part in str(text).split(",")]
    if not all(part.isascii() and part.isdigit() for part in parts) or len(parts) > 2:
        raise ValueError(f"bad start '{text}': expected a corner 0-3 or a cell ROW,COL")
    if len(parts) == 2:
        return (int(parts[0]), int(parts[1]))
    corner = int(parts[0])
    if corner >= N_CORNERS:
        raise ValueError(f"bad start '{text}': corners are 0-{N_CORNERS - 1}")
    return corner


START_HELP = (
    f"a corner 0-{N_CORNERS - 1} of the valid space or a cell ROW,COL of the 0.1 m grid "
    f"(free, in valid space, {WorldConfig().start_clearance_cells} cells clear of walls, "
    "connected to the largest part of the building)"
)


def add_start_argument(parser: argparse.ArgumentParser, default: StartSpec | None, help: str):
    """A `--start CORNER|ROW,COL` flag into `args.start` (`parse_start`'s errors shown as
    argparse's); `help` says what the start is for, the accepted forms are added."""
    parser.add_argument(
        "--start",
        type=argparse_type(parse_start),
        default=default,
        metavar="CORNER|ROW,COL",
        help=f"{help}: {START_HELP}",
    )


def normalise_start(start: StartSpec | np.integer | np.ndarray) -> StartSpec:
    """A corner as a Python int, a cell as a tuple of two Python ints."""
    if np.ndim(start) == 0:
        return int(start)
    row, col = (int(v) for v in np.asarray(start).reshape(2))
    return (row, col)


def start_argument(start: StartSpec) -> str:
    """The command-line form of a start, as `parse_start` reads it."""
    return str(start) if isinstance(start, int) else f"{start[0]},{start[1]}"


def start_label(start: StartSpec) -> str:
    """The start's part of a run name: `start2` or `start-r15c380`."""
    return f"start{start}" if isinstance(start, int) else f"start-r{start[0]}c{start[1]}"


def start_cell(world: World, start: StartSpec, clearance_cells: int) -> Cell:
    """The cell of `start` in `world`; WorldError (one line naming map and cell) when an
    explicit cell is outside the map, on a wall, outside valid space, not connected to the
    main free space (a closed room) or without clearance."""
    start = normalise_start(start)
    if isinstance(start, int):
        if not 0 <= start < N_CORNERS:
            raise WorldError(
                f"world '{world.name}': start {start} is not a corner 0-{N_CORNERS - 1}"
            )
        return start_poses(world, clearance_cells)[start]
    row, col = int(start[0]), int(start[1])
    where = f"world '{world.name}': start cell ({row}, {col})"
    rows, cols = world.shape
    if not (0 <= row < rows and 0 <= col < cols):
        raise WorldError(f"{where} is outside the map ({rows} x {cols} cells)")
    if world.occupancy[row, col]:
        raise WorldError(f"{where} is on a wall")
    if not world.valid_space[row, col]:
        raise WorldError(f"{where} is outside the valid space")
    if not main_free_space(world)[row, col]:
        raise WorldError(
            f"{where} is not connected to the largest free space of the world (a closed room?)"
        )
    if not eligible_start_cells(world, clearance_cells)[row, col]:
        raise WorldError(f"{where} has less than {clearance_cells} cells of clearance to a wall")
    return (row, col)


def start_spec_of(world: World, cell: Cell, clearance_cells: int) -> StartSpec:
    """The corner index whose start is `cell`, else the cell itself."""
    cell = (int(cell[0]), int(cell[1]))
    corners = start_poses(world, clearance_cells)
    return corners.index(cell) if cell in corners else cell


def start_poses(world: World, clearance_cells: int) -> list[Cell]:
    """Four starts: the eligible cells nearest to the top-left, top-right, bottom-left and
    bottom-right corner of the valid space (module doc).

    Two corners may share a start on a tiny map; WorldError when no cell qualifies.
    """
    if clearance_cells < 0:
        raise ValueError(f"clearance_cells must be >= 0, got {clearance_cells}")
    rows, cols = np.nonzero(eligible_start_cells(world, clearance_cells))
    if rows.size == 0:
        raise WorldError(
            f"world '{world.name}': no free valid cell with {clearance_cells} cells of clearance "
            "in the free space connected to the largest part of the building"
        )
    return [_nearest(rows, cols, corner) for corner in _valid_space_corners(world)]


def eligible_start_cells(world: World, clearance_cells: int) -> np.ndarray:
    """Bool map of the cells a robot may start on: free, valid, `clearance_cells` clear of any
    wall and in the main free space (`main_free_space`)."""
    free = ~world.occupancy
    walled = np.pad(free, 1, constant_values=False)  # the map edge is a wall
    wall_distance = ndimage.distance_transform_edt(walled)[1:-1, 1:-1]
    clear = free & world.valid_space & (wall_distance >= clearance_cells + 1)
    return clear & main_free_space(world)


def main_free_space(world: World) -> np.ndarray:
    """Bool map of the free space connected to the largest part of the building, for the
    robot: the 4-connected component of drivable cells (free, out of the planner's wall
    inflation, `NavigationConfig.wall_inflation_cells`) holding the most valid cells (ties:
    the first in row-major order), with the free cells within the inflation around it. A
    world with no drivable valid cell falls back to its free cells' components; all False
    when no free cell is valid."""
    free = ~world.occupancy
    radius = ROBOT_WALL_INFLATION_CELLS
    square = np.ones((2 * radius + 1, 2 * radius + 1), dtype=bool)
    drivable = free & ~ndimage.binary_dilation(world.occupancy, square)
    main = _largest_part(drivable, world.valid_space)
    if main.any():
        return ndimage.binary_dilation(main, square) & free
    return _largest_part(free, world.valid_space)


def _largest_part(cells: np.ndarray, valid_space: np.ndarray) -> np.ndarray:
    """The 4-connected component of `cells` with the most valid cells (none: all False)."""
    labels, count = ndimage.label(cells)  # 4-connected: the robot's moves (module doc)
    valid_cells = np.bincount(labels[cells & valid_space], minlength=count + 1)
    valid_cells[0] = 0  # not in `cells`
    if valid_cells.max() == 0:
        return np.zeros(cells.shape, dtype=bool)
    return labels == int(np.argmax(valid_cells))


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
