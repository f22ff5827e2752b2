"""Start poses: one near each corner of the valid space (docs/algorithms.md#worlds), or an
explicit cell.

A start is named either by a corner index 0-3 (the project's protocol) or by a cell
(row, col) on the 0.1 m grid (the start poses a published protocol lists). On the command
line: `2` or `15,380`; in run names: `start2` or `start-r15c380`.

Each corner start is the cell nearest (Euclidean; ties broken by row, then column) to a corner of
the valid-space bounding box that is free, inside valid space and has at least
`clearance_cells` free cells between it and any wall: its distance-transform value
(cell centre to the nearest wall-cell centre) is at least `clearance_cells + 1`.
Cells beyond the map edge count as walls, since the robot cannot go there either.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from mapex.config import WorldConfig, argparse_type
from mapex.grid import Cell
from mapex.worlds.base import World, WorldError

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
    f"(free, in valid space, {WorldConfig().start_clearance_cells} cells clear of walls)"
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
    explicit cell is outside the map, on a wall, outside valid space or without clearance."""
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
    if not eligible_start_cells(world, clearance_cells)[row, col]:
        raise WorldError(f"{where} has less than {clearance_cells} cells of clearance to a wall")
    return (row, col)


def start_spec_of(world: World, cell: Cell, clearance_cells: int) -> StartSpec:
    """The corner index whose start is `cell`, else the cell itself."""
    cell = (int(cell[0]), int(cell[1]))
    corners = start_poses(world, clearance_cells)
    return corners.index(cell) if cell in corners else cell


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
