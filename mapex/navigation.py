"""Navigation helpers of the explorer (docs/algorithms.md#navigation): cost map, planning, path
following.

The robot plans only through known-free cells, keeps one cell (3x3) away from known
walls and pays an extra cost near them (distance transform), so it never enters
unknown space and never touches a wall. Pure functions; the explorer owns the state.
"""

from __future__ import annotations

import cv2
import numpy as np

from mapex.config import NavigationConfig
from mapex.grid import FREE, OCCUPIED, UNKNOWN, Cell
from mapex.search import astar, reachable_mask

__all__ = [
    "NavigationError",
    "advance_along_path",
    "cost_map",
    "path_is_clear",
    "plan_path",
    "reachable_mask",
    "unknown_within",
]


class NavigationError(ValueError):
    """Bad input to a navigation helper; the message names the cause."""


def cost_map(observed: np.ndarray, config: NavigationConfig) -> np.ndarray:
    """Planning cost map, float32: inf = not passable, else the cost (>= 1) of entering a cell.

    Passable: known FREE and not within `wall_inflation_cells` (square) of a known
    OCCUPIED cell. Cost: 1 + wall_cost_weight * max(0, clearance - d) / clearance with d
    the Euclidean distance in cells to the nearest known OCCUPIED cell (unknown cells
    never count as walls).
    """
    if observed.ndim != 2 or observed.dtype != np.uint8:
        raise NavigationError(
            f"observed map must be 2-D uint8, got {observed.dtype} {observed.shape}"
        )
    if config.wall_clearance_cells <= 0:
        raise NavigationError("wall_clearance_cells must be positive")
    walls = (observed == OCCUPIED).view(np.uint8)
    passable = observed == FREE
    radius = config.wall_inflation_cells
    if radius > 0:
        kernel = np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8)
        passable &= cv2.dilate(walls, kernel) == 0
    # Exact Euclidean distance to the nearest wall (a huge value when there is none).
    distance = cv2.distanceTransform(1 - walls, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    clearance = np.float32(config.wall_clearance_cells)
    closeness = np.maximum(clearance - distance, 0) / clearance
    cost = 1 + np.float32(config.wall_cost_weight) * closeness
    return np.where(passable, cost, np.float32(np.inf)).astype(np.float32, copy=False)


def plan_path(observed: np.ndarray, cost: np.ndarray, start: Cell, goal: Cell) -> np.ndarray | None:
    """A* path int32 (N, 2) from the robot cell to `goal`; None if the goal is not known
    FREE or cannot be reached."""
    goal_r, goal_c = int(goal[0]), int(goal[1])
    if not (0 <= goal_r < observed.shape[0] and 0 <= goal_c < observed.shape[1]):
        return None
    if observed[goal_r, goal_c] != FREE:
        return None
    return astar(cost, start, (goal_r, goal_c))


def path_is_clear(observed: np.ndarray, path: np.ndarray, config: NavigationConfig) -> bool:
    """Whether the path can still be followed: every cell after the robot's own is passable
    under the rule of `cost_map` (known FREE, no known OCCUPIED within the inflation square),
    checked on the path cells only so no whole cost map is built. The last cell (the goal)
    is exempt, as in `astar`: a known-free goal may sit inside the wall inflation, and a
    known-free cell never becomes a wall.
    """
    inner = np.asarray(path)[1:-1]
    return bool(_cells_passable(observed, inner, config.wall_inflation_cells).all())


def _cells_passable(observed: np.ndarray, cells: np.ndarray, radius: int) -> np.ndarray:
    """Per cell (k, 2): known FREE and no known OCCUPIED cell in its (2r+1)^2 square."""
    if len(cells) == 0:
        return np.ones(0, dtype=bool)
    offsets = np.arange(-radius, radius + 1)
    rows = cells[:, 0, None, None] + offsets[None, :, None]
    cols = cells[:, 1, None, None] + offsets[None, None, :]
    inside = (rows >= 0) & (rows < observed.shape[0]) & (cols >= 0) & (cols < observed.shape[1])
    window = observed[rows.clip(0, observed.shape[0] - 1), cols.clip(0, observed.shape[1] - 1)]
    near_wall = ((window == OCCUPIED) & inside).any(axis=(1, 2))
    return (observed[cells[:, 0], cells[:, 1]] == FREE) & ~near_wall


def advance_along_path(path: np.ndarray, cells_per_step: int) -> tuple[np.ndarray, np.ndarray]:
    """Move up to `cells_per_step` moves along `path` (path[0] = robot cell).

    Returns the cells moved through this step, int (k, 2) ending at the new robot cell
    (k = 0 when already at the end), and the remaining path starting at the new robot cell.
    """
    path = np.asarray(path)
    if path.ndim != 2 or path.shape[1] != 2 or len(path) == 0:
        raise NavigationError(f"path must be a non-empty (N, 2) array, got shape {path.shape}")
    if cells_per_step < 0:
        raise NavigationError(f"cells_per_step must be >= 0, got {cells_per_step}")
    moves = min(cells_per_step, len(path) - 1)
    return path[1 : moves + 1].copy(), path[moves:].copy()


def unknown_within(observed: np.ndarray, cell: Cell, radius_cells: float) -> bool:
    """Whether any UNKNOWN cell lies within Euclidean `radius_cells` of `cell` (goal-drop rule)."""
    r, c = int(cell[0]), int(cell[1])
    reach = int(np.floor(radius_cells))
    r0, r1 = max(r - reach, 0), min(r + reach + 1, observed.shape[0])
    c0, c1 = max(c - reach, 0), min(c + reach + 1, observed.shape[1])
    rows, cols = np.ogrid[r0:r1, c0:c1]
    in_disc = (rows - r) ** 2 + (cols - c) ** 2 <= radius_cells**2
    return bool((observed[r0:r1, c0:c1][in_disc] == UNKNOWN).any())
