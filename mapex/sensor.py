"""The noise-free 2D LiDAR of docs/algorithms.md#sensor and its integration into the observed map.

A ray walks cells with the shared traversal of `mapex.raycast` from the robot's cell and stops
at the first wall (included), at the range or at the map border. A `Scan` keeps only what
the observed map needs, per ray the number of cells walked and whether the last one is a wall,
so it is compact on the network and retracing it on the observed map gives exactly the cells
the scan saw: no wall cell is ever marked free.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass

import numpy as np
from numba import njit

from mapex.config import SensorConfig
from mapex.grid import FREE, OCCUPIED, Cell
from mapex.raycast import inside, next_cell, ray_directions, ray_through, start_state

_MAX_COUNT = np.iinfo(np.uint16).max


@dataclass(frozen=True)
class Scan:
    """One LiDAR scan taken at `pose` (row, col).

    n_cells: uint16 (n_rays,), cells ray k walked, start cell and hit cell included.
    hit: bool (n_rays,), whether the last cell of ray k is a wall.
    The arrays are made read-only.
    """

    pose: Cell
    n_cells: np.ndarray
    hit: np.ndarray

    def __post_init__(self) -> None:
        if self.n_cells.dtype != np.uint16 or self.hit.dtype != np.bool_:
            raise ValueError("scan arrays must be n_cells uint16 and hit bool")
        if self.n_cells.ndim != 1 or self.n_cells.shape != self.hit.shape:
            raise ValueError(
                f"scan arrays must be 1-D of one length, got {self.n_cells.shape} and "
                f"{self.hit.shape}"
            )
        self.n_cells.flags.writeable = False
        self.hit.flags.writeable = False

    @property
    def n_rays(self) -> int:
        return len(self.n_cells)


def cast_scan(occupancy: np.ndarray, pose: Cell, config: SensorConfig) -> Scan:
    """Scan the ground truth `occupancy` (bool, True = wall) from the free cell `pose`."""
    return _cast(occupancy, np.empty((0, 0), dtype=np.uint8), False, pose, config)


def integrate_scan(
    observed: np.ndarray, scan: Scan, config: SensorConfig, seen: np.ndarray | None = None
) -> None:
    """Mark the cells of `scan` in `observed` (uint8 codes, in place).

    Every walked cell becomes FREE except the last cell of a hit ray, which becomes OCCUPIED;
    an OCCUPIED cell is never turned FREE. `seen` (bool, the map's shape), when given, gets
    every walked cell set True in the same pass (a team's record of who saw what). A scan
    that does not fit this map and config raises ValueError (the map may then be partly
    updated).
    """
    _check_observed(observed, observed.shape)
    mark_seen = seen is not None
    if not mark_seen:
        seen = np.zeros((0, 0), dtype=np.bool_)
    elif seen.dtype != np.bool_ or seen.shape != observed.shape:
        raise ValueError(f"seen must be bool {observed.shape}, got {seen.dtype} {seen.shape}")
    row, col = _checked_pose(observed, scan.pose)
    _check_config(config)
    if scan.n_rays != config.n_rays:
        raise ValueError(f"scan has {scan.n_rays} rays, the sensor config {config.n_rays}")
    if scan.n_cells.min(initial=1) < 1:
        raise ValueError("every scan ray walks at least its start cell (n_cells >= 1)")
    directions = ray_directions(config.n_rays)
    bad_rays = _retrace_kernel(
        observed, seen, mark_seen, row, col, directions, config.range_cells, scan.n_cells,
        scan.hit,
    )  # fmt: skip
    if bad_rays:
        raise ValueError(f"{bad_rays} scan rays run past the range or the map border")


def scan_and_integrate(
    occupancy: np.ndarray, observed: np.ndarray, pose: Cell, config: SensorConfig
) -> Scan:
    """`cast_scan` and `integrate_scan` in one pass: same scan, same observed map, faster."""
    _check_observed(observed, occupancy.shape)
    return _cast(occupancy, observed, True, pose, config)


def _cast(
    occupancy: np.ndarray, observed: np.ndarray, integrate: bool, pose: Cell, config: SensorConfig
) -> Scan:
    """Cast a scan from `pose`, marking `observed` too when `integrate`."""
    row, col = _checked_free_pose(occupancy, pose)
    _check_config(config)
    n_cells = np.empty(config.n_rays, dtype=np.uint16)
    hit = np.empty(config.n_rays, dtype=np.bool_)
    directions = ray_directions(config.n_rays)
    _scan_kernel(
        occupancy, observed, integrate, row, col, directions, config.range_cells, n_cells, hit
    )
    return Scan((row, col), n_cells, hit)


def _checked_pose(grid: np.ndarray, pose: Cell) -> tuple[int, int]:
    """`pose` as a (row, col) of Python ints inside `grid`, or ValueError."""
    try:
        row, col = (operator.index(v) for v in pose)
    except (TypeError, ValueError):
        raise ValueError(f"pose must be two integers (row, col), got {pose!r}") from None
    if not (0 <= row < grid.shape[0] and 0 <= col < grid.shape[1]):
        raise ValueError(f"pose {(row, col)} is outside the {grid.shape} map")
    return row, col


def _checked_free_pose(occupancy: np.ndarray, pose: Cell) -> tuple[int, int]:
    """`pose` checked to be a free cell of the bool ground truth `occupancy`."""
    if occupancy.dtype != np.bool_ or occupancy.ndim != 2:
        raise ValueError(
            f"occupancy must be a 2-D bool map, got {occupancy.dtype} {occupancy.shape}"
        )
    row, col = _checked_pose(occupancy, pose)
    if occupancy[row, col]:
        raise ValueError(f"pose {(row, col)} is in a wall")
    return row, col


def _check_config(config: SensorConfig) -> None:
    """Ray counts must fit the uint16 `Scan.n_cells` (a ray walks < 2 * range + 4 cells)."""
    if config.n_rays < 1 or not 0 <= config.range_cells <= (_MAX_COUNT - 4) // 2:
        raise ValueError(f"sensor config out of bounds: {config}")


def _check_observed(observed: np.ndarray, shape: tuple[int, ...]) -> None:
    """The observed map must be a 2-D uint8 map of `shape`, updated in place."""
    if observed.dtype != np.uint8 or observed.ndim != 2 or observed.shape != shape:
        raise ValueError(
            f"observed map must be uint8 {shape}, got {observed.dtype} {observed.shape}"
        )


@njit(cache=True)
def _scan_kernel(occupancy, observed, integrate, row0, col0, directions, range_cells, n_cells, hit):
    """Cast every ray; fill n_cells and hit; mark `observed` too when `integrate`."""
    n_rows, n_cols = occupancy.shape
    for k in range(directions.shape[0]):
        ray = ray_through(directions[k, 0], directions[k, 1])
        state = start_state(row0, col0)
        count = 1
        while True:
            row, col = state[0], state[1]
            if occupancy[row, col]:
                if integrate:
                    observed[row, col] = OCCUPIED
                hit[k] = True
                break
            if integrate and observed[row, col] != OCCUPIED:
                observed[row, col] = FREE
            state, t = next_cell(ray, state)
            if t > range_cells or not inside(n_rows, n_cols, state[0], state[1]):
                hit[k] = False
                break
            count += 1
        n_cells[k] = count


@njit(cache=True)
def _retrace_kernel(
    observed, seen, mark_seen, row0, col0, directions, range_cells, n_cells, hit
) -> int:
    """Mark each ray's n_cells cells on `observed` (and `seen` when `mark_seen`); return how
    many rays did not fit."""
    n_rows, n_cols = observed.shape
    bad_rays = 0
    for k in range(directions.shape[0]):
        ray = ray_through(directions[k, 0], directions[k, 1])
        state = start_state(row0, col0)
        last = int(n_cells[k]) - 1
        for i in range(last + 1):
            row, col = state[0], state[1]
            if i == last and hit[k]:
                observed[row, col] = OCCUPIED
            elif observed[row, col] != OCCUPIED:
                observed[row, col] = FREE
            if mark_seen:
                seen[row, col] = True
            if i < last:
                state, t = next_cell(ray, state)
                if t > range_cells or not inside(n_rows, n_cols, state[0], state[1]):
                    bad_rays += 1
                    break
    return bad_rays
