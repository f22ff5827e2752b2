"""Grid shortest paths: A*, a Dijkstra shortest-path tree and an 8-connected flood fill.

Cost maps are float32 (rows, cols): `np.inf` = blocked, otherwise the cost of *entering*
that cell (>= 1 by the project's convention; any positive value works). A move costs the
entered cell's cost times 1 (orthogonal) or sqrt(2) (diagonal), 8-connected with no corner
cutting (docs/algorithms.md#navigation). The start cell (and A*'s goal cell) count as
passable even when blocked in the map; entering such a cell costs the map's minimum finite
cost. Ties go by priority, then (A*) the smaller heuristic, then the smaller flat cell
index. The priority queue is a binary heap in numba arrays (stale entries skipped on pop).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mapex.grid import Cell


class SearchError(ValueError):
    """A cost map or cell that the search cannot work with; the message names the cause."""


SQRT2 = np.sqrt(2.0)
_HEAP_START_CAPACITY = 4096  # grows by doubling; only a memory/speed trade-off


# ----------------------------------------------------------------------------- numba kernels
# The kernels work on a copy of the map padded with a blocked border and flattened, so a
# neighbour is `node + offset` without bounds checks. Padded width = cols + 2. Passability
# is a separate bool array: it is read most often and a small array stays in cache.


@njit(cache=True)
def _padded_cost(cost, start_r, start_c, goal_r, goal_c):
    """Flat padded (cost float32, passable bool, min_cost). Blocked endpoints become
    passable at the minimum finite cost (1.0 when none); goal_r < 0 means no goal."""
    rows, cols = cost.shape
    width = cols + 2
    padded = np.full((rows + 2) * width, np.inf, dtype=np.float32)
    min_cost = np.inf
    for r in range(rows):
        for c in range(cols):
            value = cost[r, c]
            padded[(r + 1) * width + c + 1] = value
            min_cost = min(min_cost, value)
    if not np.isfinite(min_cost):
        min_cost = 1.0
    for r, c in ((start_r, start_c), (goal_r, goal_c)):
        cell = (r + 1) * width + c + 1
        if r >= 0 and not np.isfinite(padded[cell]):
            padded[cell] = min_cost
    return padded, padded < np.inf, min_cost


@njit(cache=True, inline="always")
def _move_tables(width):
    """The 8 moves in a fixed order (orthogonal first): flat offset of the target, flat
    offsets of the two orthogonal cells a diagonal move passes, and the move length.

    For orthogonal moves both "via" offsets are 0 (the current cell, always passable), so
    one test covers every move: target and both via cells passable (no corner cutting).
    Written out in each kernel: a helper taking the arrays costs refcounting per call.
    """
    target = np.array([-width, width, -1, 1, -width - 1, -width + 1, width - 1, width + 1])
    via_row = np.array([0, 0, 0, 0, -width, -width, width, width])
    via_col = np.array([0, 0, 0, 0, -1, 1, -1, 1])
    length = np.array([1.0, 1.0, 1.0, 1.0, SQRT2, SQRT2, SQRT2, SQRT2])
    return target, via_row, via_col, length


@njit(cache=True, inline="always")
def _before(key_a, tie_a, node_a, key_b, tie_b, node_b):
    """Heap order: priority, then tie value, then cell index (deterministic)."""
    if key_a != key_b:
        return key_a < key_b
    if tie_a != tie_b:
        return tie_a < tie_b
    return node_a < node_b


@njit(cache=True, inline="always")
def _heap_push(keys, ties, nodes, size, key, tie, node):
    """Push onto the binary heap (capacity must allow it); returns the new size."""
    i = size
    while i > 0:
        up = (i - 1) >> 1
        if not _before(key, tie, node, keys[up], ties[up], nodes[up]):
            break
        keys[i], ties[i], nodes[i] = keys[up], ties[up], nodes[up]
        i = up
    keys[i], ties[i], nodes[i] = key, tie, node
    return size + 1


@njit(cache=True, inline="always")
def _heap_pop(keys, ties, nodes, size):
    """Remove the top entry; returns (its node, the new size)."""
    top = nodes[0]
    size -= 1
    key, tie, node = keys[size], ties[size], nodes[size]
    i = 0
    while True:
        child = 2 * i + 1
        if child >= size:
            break
        right = child + 1
        if right < size and _before(
            keys[right], ties[right], nodes[right], keys[child], ties[child], nodes[child]
        ):
            child = right
        if not _before(keys[child], ties[child], nodes[child], key, tie, node):
            break
        keys[i], ties[i], nodes[i] = keys[child], ties[child], nodes[child]
        i = child
    if size > 0:
        keys[i], ties[i], nodes[i] = key, tie, node
    return top, size


@njit(cache=True, inline="always")
def _heap_room(keys, ties, nodes, size):
    """The heap arrays, doubled when the 8 pushes of one expansion might not fit."""
    if size + 8 > nodes.size:
        keys = np.concatenate((keys, np.empty_like(keys)))
        ties = np.concatenate((ties, np.empty_like(ties)))
        nodes = np.concatenate((nodes, np.empty_like(nodes)))
    return keys, ties, nodes


@njit(cache=True, inline="always")
def _octile(node, goal_r, goal_c, width):
    dr = abs(node // width - goal_r)
    dc = abs(node % width - goal_c)
    return max(dr, dc) + (SQRT2 - 1.0) * min(dr, dc)


@njit(cache=True)
def _best_first(padded, passable, width, start, goal, h_scale):
    """A* from `start` to `goal` (padded flat cells), or Dijkstra over all cells if goal < 0.

    Lazy-deletion heap; the heuristic (octile x h_scale, h_scale = minimum finite cost)
    is consistent, so a cell is final when first popped. Returns (g float64, parent int32),
    padded flat.
    """
    n_cells = padded.size
    target, via_row, via_col, length = _move_tables(width)
    goal_r, goal_c = goal // width, goal % width
    g = np.full(n_cells, np.inf)
    parent = np.full(n_cells, -1, dtype=np.int32)
    closed = np.zeros(n_cells, dtype=np.bool_)
    keys = np.empty(_HEAP_START_CAPACITY)
    ties = np.empty(_HEAP_START_CAPACITY)
    nodes = np.empty(_HEAP_START_CAPACITY, dtype=np.int64)
    g[start] = 0.0
    size = _heap_push(keys, ties, nodes, 0, 0.0, 0.0, start)
    while size > 0:
        node, size = _heap_pop(keys, ties, nodes, size)
        if closed[node]:
            continue
        closed[node] = True
        if node == goal:
            break
        keys, ties, nodes = _heap_room(keys, ties, nodes, size)
        for k in range(8):
            nxt = node + target[k]
            if closed[nxt] or not passable[nxt]:
                continue
            if not (passable[node + via_row[k]] and passable[node + via_col[k]]):
                continue
            candidate = g[node] + padded[nxt] * length[k]
            if candidate < g[nxt]:
                g[nxt] = candidate
                parent[nxt] = node
                h = h_scale * _octile(nxt, goal_r, goal_c, width) if goal >= 0 else 0.0
                size = _heap_push(keys, ties, nodes, size, candidate + h, h, nxt)
    return g, parent


@njit(cache=True)
def _unpad_tree(g, parent, rows, cols):
    """Padded flat (g, parent) -> float32 (rows, cols) distances and int32 unpadded parents."""
    width = cols + 2
    dist = np.empty((rows, cols), dtype=np.float32)
    tree = np.empty((rows, cols), dtype=np.int32)
    for r in range(rows):
        for c in range(cols):
            cell = (r + 1) * width + c + 1
            dist[r, c] = g[cell]
            up = parent[cell]
            tree[r, c] = -1 if up < 0 else (up // width - 1) * cols + up % width - 1
    return dist, tree


@njit(cache=True)
def _trace_path(parent, width, offset, goal):
    """Cells from the tree root to `goal` inclusive, int32 (N, 2); a flat cell f is
    (f // width - offset, f % width - offset)."""
    length = 1
    node = goal
    while parent[node] >= 0:
        node = parent[node]
        length += 1
    path = np.empty((length, 2), dtype=np.int32)
    node = goal
    for i in range(length - 1, -1, -1):
        path[i, 0] = node // width - offset
        path[i, 1] = node % width - offset
        node = parent[node]
    return path


@njit(cache=True)
def _flood_fill(passable, width, start):
    """Flat padded bool map of the cells reachable from `start` (breadth-first)."""
    target, via_row, via_col, _ = _move_tables(width)
    reached = np.zeros(passable.size, dtype=np.bool_)
    queue = np.empty(passable.size, dtype=np.int64)
    reached[start] = True
    queue[0] = start
    head, tail = 0, 1
    while head < tail:
        node = queue[head]
        head += 1
        for k in range(8):
            nxt = node + target[k]
            if reached[nxt] or not passable[nxt]:
                continue
            if not (passable[node + via_row[k]] and passable[node + via_col[k]]):
                continue
            reached[nxt] = True
            queue[tail] = nxt
            tail += 1
    return reached


# ----------------------------------------------------------------------------- Python wrappers


def _checked_cost(cost: np.ndarray) -> np.ndarray:
    cost = np.ascontiguousarray(cost, dtype=np.float32)
    if cost.ndim != 2 or cost.size == 0:
        raise SearchError(f"cost map must be a non-empty 2-D array, got shape {cost.shape}")
    if np.isnan(cost).any() or (cost <= 0).any():
        raise SearchError("cost map entries must be positive or inf (no NaN, no <= 0)")
    return cost


def _checked_cell(cell: Cell | np.ndarray, shape: tuple[int, ...], what: str) -> tuple[int, int]:
    r, c = int(cell[0]), int(cell[1])
    if not (0 <= r < shape[0] and 0 <= c < shape[1]):
        raise SearchError(f"{what} cell {(r, c)} is outside the map of shape {shape}")
    return r, c


def astar(cost: np.ndarray, start: Cell, goal: Cell) -> np.ndarray | None:
    """Cheapest 8-connected path, int32 (N, 2) from start to goal inclusive; None if unreachable.

    Start and goal are passable even when blocked in `cost` (the robot's own cell, a
    known-free goal next to a wall).
    """
    cost = _checked_cost(cost)
    start_r, start_c = _checked_cell(start, cost.shape, "start")
    goal_r, goal_c = _checked_cell(goal, cost.shape, "goal")
    padded, passable, min_cost = _padded_cost(cost, start_r, start_c, goal_r, goal_c)
    width = cost.shape[1] + 2
    goal_flat = (goal_r + 1) * width + goal_c + 1
    start_flat = (start_r + 1) * width + start_c + 1
    g, parent = _best_first(padded, passable, width, start_flat, goal_flat, min_cost)
    if not np.isfinite(g[goal_flat]):
        return None
    return _trace_path(parent, width, 1, goal_flat)


def shortest_path_tree(cost: np.ndarray, start: Cell) -> tuple[np.ndarray, np.ndarray]:
    """Dijkstra from `start` over the whole map (start passable even if blocked).

    Returns the float32 path-cost map (inf where unreachable) and the int32 parent map
    (flat index of each cell's predecessor; -1 for the start and unreachable cells).
    """
    cost = _checked_cost(cost)
    start_r, start_c = _checked_cell(start, cost.shape, "start")
    padded, passable, _ = _padded_cost(cost, start_r, start_c, -1, -1)
    width = cost.shape[1] + 2
    g, parent = _best_first(padded, passable, width, (start_r + 1) * width + start_c + 1, -1, 0.0)
    return _unpad_tree(g, parent, *cost.shape)


def path_from_tree(parent: np.ndarray, goal: Cell, start: Cell | None = None) -> np.ndarray | None:
    """Path int32 (N, 2) from the tree root to `goal` inclusive, or None if `goal` is unreachable.

    A cell with parent -1 is either the root or unreachable: pass `start` to get the
    one-cell path [start] for goal == start (without it such a goal gives None).
    """
    goal_r, goal_c = _checked_cell(goal, parent.shape, "goal")
    cols = parent.shape[1]
    flat_parent = np.ascontiguousarray(parent, dtype=np.int32).ravel()
    goal_flat = goal_r * cols + goal_c
    if flat_parent[goal_flat] < 0:
        is_start = start is not None and (int(start[0]), int(start[1])) == (goal_r, goal_c)
        return np.array([[goal_r, goal_c]], dtype=np.int32) if is_start else None
    return _trace_path(flat_parent, cols, 0, goal_flat)


def reachable_mask(cost: np.ndarray, start: Cell) -> np.ndarray:
    """Bool map of the cells reachable from `start` with the same move rules as `astar`.

    The start counts as passable even when blocked; no goal exception applies here.
    """
    cost = _checked_cost(cost)
    start_r, start_c = _checked_cell(start, cost.shape, "start")
    _, passable, _ = _padded_cost(cost, start_r, start_c, -1, -1)
    width = cost.shape[1] + 2
    reached = _flood_fill(passable, width, (start_r + 1) * width + start_c + 1)
    return reached.reshape(-1, width)[1:-1, 1:-1].copy()
