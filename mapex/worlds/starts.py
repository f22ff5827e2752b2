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
from collections.abc import Sequence

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
    return start_cells(world, [start], clearance_cells)[0]


# why an explicit start cell is refused, in the order `start_cells` judges it
_OUTSIDE, _WALL, _INVALID, _CLOSED, _CRAMPED = 1, 2, 3, 4, 5
# explicit cells are clipped to this before they become an array: a start of 10**30 (a
# starts file's JSON may hold one) is outside the map, not an overflow
_FAR = 2**62


def start_cells(world: World, starts: Sequence[StartSpec], clearance_cells: int) -> list[Cell]:
    """The cell of each start of `starts` in `world`, all judged at once by `start_cell`'s
    rules: the maps they are judged on (main free space, eligible cells, the four corner
    starts) are computed once, whatever the number of starts, and the explicit cells are
    looked up in them as one array. WorldError (one line) for the first start, in order,
    that `start_cell` refuses, with its message."""
    specs = [start if _is_normal(start) else normalise_start(start) for start in starts]
    maps = _StartMaps(world, clearance_cells)
    explicit = [i for i, spec in enumerate(specs) if not isinstance(spec, int)]
    try:
        cells = np.array([specs[i] for i in explicit], dtype=np.int64).reshape(-1, 2)
    except OverflowError:
        far = [[max(-_FAR, min(_FAR, v)) for v in specs[i]] for i in explicit]
        cells = np.array(far, dtype=np.int64).reshape(-1, 2)
    reasons = maps.refusals(cells)
    refused = np.flatnonzero(reasons)
    first_refused = explicit[int(refused[0])] if refused.size else len(specs)
    for spec in specs[:first_refused]:  # the corners before it, judged as one by one would
        if isinstance(spec, int) and not 0 <= spec < N_CORNERS:
            raise WorldError(
                f"world '{world.name}': start {spec} is not a corner 0-{N_CORNERS - 1}"
            )
        if isinstance(spec, int):
            maps.corners()  # computed once; WorldError when no cell qualifies
    if refused.size:
        raise WorldError(maps.refusal(specs[first_refused], int(reasons[refused[0]])))
    return [maps.corners()[s] if isinstance(s, int) else (int(s[0]), int(s[1])) for s in specs]


def _is_normal(start: object) -> bool:
    """Whether `start` is as `normalise_start` makes it already (a file's cells are)."""
    if type(start) is int:
        return True
    return type(start) is tuple and len(start) == 2 and all(type(v) is int for v in start)


class _StartMaps:
    """The maps starts on `world` are judged on, each computed once, when first needed."""

    def __init__(self, world: World, clearance_cells: int) -> None:
        self.world = world
        self.clearance_cells = clearance_cells
        self._main: np.ndarray | None = None
        self._eligible: np.ndarray | None = None
        self._corners: list[Cell] | None = None

    def main(self) -> np.ndarray:
        if self._main is None:
            self._main = main_free_space(self.world)
        return self._main

    def eligible(self) -> np.ndarray:
        if self._eligible is None:
            self._eligible = _eligible(self.world, self.clearance_cells, self.main())
        return self._eligible

    def corners(self) -> list[Cell]:
        if self._corners is None:
            self._corners = _poses(self.world, self.eligible(), self.clearance_cells)
        return self._corners

    def refusals(self, cells: np.ndarray) -> np.ndarray:
        """Per row (row, col) of `cells`: 0 when a robot may start there, else why not
        (`_OUTSIDE` ... `_CRAMPED`, the first rule it fails)."""
        rows, cols = self.world.shape
        r, c = cells[:, 0], cells[:, 1]
        inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
        r, c = np.where(inside, r, 0), np.where(inside, c, 0)
        reasons = np.where(inside, 0, _OUTSIDE)
        reasons[(reasons == 0) & self.world.occupancy[r, c].astype(bool)] = _WALL
        reasons[(reasons == 0) & ~self.world.valid_space[r, c].astype(bool)] = _INVALID
        if (reasons == 0).any():
            reasons[(reasons == 0) & ~self.main()[r, c]] = _CLOSED
        if (reasons == 0).any():
            reasons[(reasons == 0) & ~self.eligible()[r, c]] = _CRAMPED
        return reasons

    def refusal(self, cell: tuple[int, int], reason: int) -> str:
        """`start_cell`'s line for the explicit `cell` refused for `reason`."""
        rows, cols = self.world.shape
        where = f"world '{self.world.name}': start cell ({cell[0]}, {cell[1]})"
        why = {
            _OUTSIDE: f"is outside the map ({rows} x {cols} cells)",
            _WALL: "is on a wall",
            _INVALID: "is outside the valid space",
            _CLOSED: "is not connected to the largest free space of the world (a closed room?)",
            _CRAMPED: f"has less than {self.clearance_cells} cells of clearance to a wall",
        }
        return f"{where} {why[reason]}"


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
    return _poses(world, eligible_start_cells(world, clearance_cells), clearance_cells)


def _poses(world: World, eligible: np.ndarray, clearance_cells: int) -> list[Cell]:
    """`start_poses` given the world's `eligible_start_cells`."""
    if clearance_cells < 0:
        raise ValueError(f"clearance_cells must be >= 0, got {clearance_cells}")
    rows, cols = np.nonzero(eligible)
    if rows.size == 0:
        raise WorldError(
            f"world '{world.name}': no free valid cell with {clearance_cells} cells of clearance "
            "in the free space connected to the largest part of the building"
        )
    return [_nearest(rows, cols, corner) for corner in _valid_space_corners(world)]


def eligible_start_cells(world: World, clearance_cells: int) -> np.ndarray:
    """Bool map of the cells a robot may start on: free, valid, `clearance_cells` clear of any
    wall and in the main free space (`main_free_space`)."""
    return _eligible(world, clearance_cells, main_free_space(world))


def _eligible(world: World, clearance_cells: int, main: np.ndarray) -> np.ndarray:
    """`eligible_start_cells` given the world's `main_free_space`."""
    free = ~world.occupancy
    walled = np.pad(free, 1, constant_values=False)  # the map edge is a wall
    wall_distance = ndimage.distance_transform_edt(walled)[1:-1, 1:-1]
    clear = free & world.valid_space & (wall_distance >= clearance_cells + 1)
    return clear & main


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
