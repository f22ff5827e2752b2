"""A*, the shortest-path tree and the flood fill against an independent brute-force reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapex.search import SearchError, astar, path_from_tree, reachable_mask, shortest_path_tree

MOVES = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
SEEDS = range(60)


def reference_distances(cost: np.ndarray, start, goal=None) -> np.ndarray:
    """Bellman-Ford by repeated full relaxation: slow, obviously correct.

    Endpoints (start, optional goal) are passable; entering a blocked endpoint costs the
    minimum finite cost of the map (1 when there is none).
    """
    rows, cols = cost.shape
    finite = cost[np.isfinite(cost)]
    min_cost = float(finite.min()) if finite.size else 1.0
    endpoints = {tuple(start)} | ({tuple(goal)} if goal is not None else set())

    def passable(r, c):
        inside = 0 <= r < rows and 0 <= c < cols
        return inside and (math.isfinite(cost[r, c]) or (r, c) in endpoints)

    dist = np.full(cost.shape, np.inf)
    dist[tuple(start)] = 0.0
    changed = True
    while changed:
        changed = False
        for r in range(rows):
            for c in range(cols):
                if not math.isfinite(dist[r, c]):
                    continue
                for dr, dc in MOVES:
                    nr, nc = r + dr, c + dc
                    if not passable(nr, nc):
                        continue
                    if dr and dc and not (passable(r + dr, c) and passable(r, c + dc)):
                        continue
                    enter = cost[nr, nc] if math.isfinite(cost[nr, nc]) else min_cost
                    candidate = dist[r, c] + enter * (math.sqrt(2) if dr and dc else 1.0)
                    if candidate < dist[nr, nc] - 1e-12:
                        dist[nr, nc] = candidate
                        changed = True
    return dist


def random_problem(seed: int):
    """A random cost map (about a quarter blocked, costs in [1, 3]) and two random cells."""
    rng = np.random.default_rng(seed)
    rows, cols = (12, 12) if seed % 3 else tuple(rng.integers(1, 13, size=2))
    cost = rng.uniform(1.0, 3.0, size=(rows, cols)).astype(np.float32)
    cost[rng.random((rows, cols)) < 0.25] = np.inf
    start = (int(rng.integers(rows)), int(rng.integers(cols)))
    goal = (int(rng.integers(rows)), int(rng.integers(cols)))
    return cost, start, goal


def path_cost(cost: np.ndarray, path: np.ndarray) -> float:
    finite = cost[np.isfinite(cost)]
    min_cost = float(finite.min()) if finite.size else 1.0
    total = 0.0
    for (r0, c0), (r1, c1) in zip(path[:-1], path[1:], strict=True):
        enter = cost[r1, c1] if np.isfinite(cost[r1, c1]) else min_cost
        total += float(enter) * (math.sqrt(2) if r0 != r1 and c0 != c1 else 1.0)
    return total


def assert_valid_path(cost: np.ndarray, path: np.ndarray, start, goal) -> None:
    assert path.dtype == np.int32 and path.ndim == 2 and path.shape[1] == 2
    assert tuple(path[0]) == tuple(start) and tuple(path[-1]) == tuple(goal)
    endpoints = {tuple(start), tuple(goal)}

    def passable(r, c):
        return np.isfinite(cost[r, c]) or (r, c) in endpoints

    for (r0, c0), (r1, c1) in zip(path[:-1].tolist(), path[1:].tolist(), strict=True):
        assert max(abs(r1 - r0), abs(c1 - c0)) == 1, "consecutive cells must be 8-adjacent"
        assert passable(r1, c1)
        if r0 != r1 and c0 != c1:
            assert passable(r1, c0) and passable(r0, c1), "corner cut"


@pytest.mark.parametrize("seed", SEEDS)
def test_astar_matches_reference_cost_and_is_valid(seed):
    cost, start, goal = random_problem(seed)
    expected = reference_distances(cost, start, goal)[goal]
    path = astar(cost, start, goal)
    if not np.isfinite(expected):
        assert path is None
        return
    assert path is not None
    assert_valid_path(cost, path, start, goal)
    assert path_cost(cost, path) == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_shortest_path_tree_matches_reference(seed):
    cost, start, _ = random_problem(seed)
    expected = reference_distances(cost, start)
    dist, parent = shortest_path_tree(cost, start)
    assert dist.dtype == np.float32 and parent.dtype == np.int32
    np.testing.assert_array_equal(np.isfinite(dist), np.isfinite(expected))
    np.testing.assert_allclose(dist[np.isfinite(dist)], expected[np.isfinite(expected)], rtol=1e-5)
    assert parent[start] == -1
    assert np.all(parent[~np.isfinite(dist)] == -1)
    for goal in zip(*np.nonzero(np.isfinite(dist)), strict=True):
        path = path_from_tree(parent, goal, start)
        assert_valid_path(cost, path, start, start if goal == start else goal)
        assert path_cost(cost, path) == pytest.approx(float(dist[goal]), rel=1e-5)


@pytest.mark.parametrize("seed", SEEDS)
def test_reachable_mask_matches_reference(seed):
    cost, start, _ = random_problem(seed)
    expected = np.isfinite(reference_distances(cost, start))
    np.testing.assert_array_equal(reachable_mask(cost, start), expected)


def test_astar_none_when_walled_off():
    cost = np.ones((7, 7), dtype=np.float32)
    cost[3, :] = np.inf
    assert astar(cost, (0, 0), (6, 6)) is None
    assert not reachable_mask(cost, (0, 0))[6, 6]


def test_astar_start_equals_goal():
    cost = np.ones((4, 4), dtype=np.float32)
    np.testing.assert_array_equal(astar(cost, (2, 1), (2, 1)), [[2, 1]])


def test_no_corner_cutting_between_diagonal_walls():
    cost = np.ones((2, 2), dtype=np.float32)
    cost[0, 1] = cost[1, 0] = np.inf
    assert astar(cost, (0, 0), (1, 1)) is None
    cost[0, 1] = 1.0
    np.testing.assert_array_equal(astar(cost, (0, 0), (1, 1)), [[0, 0], [0, 1], [1, 1]])


def test_blocked_start_and_goal_are_passable():
    cost = np.full((1, 5), np.inf, dtype=np.float32)
    cost[0, 1:4] = 2.0
    path = astar(cost, (0, 0), (0, 4))
    np.testing.assert_array_equal(path, [[0, 0], [0, 1], [0, 2], [0, 3], [0, 4]])
    dist, _ = shortest_path_tree(cost, (0, 0))
    assert dist[0, 3] == pytest.approx(6.0) and np.isinf(dist[0, 4])


def test_astar_prefers_cheap_cells_and_is_deterministic():
    cost = np.ones((5, 9), dtype=np.float32)
    cost[2, 1:8] = 50.0  # straight line is expensive; going around row 0 or 4 is cheaper
    first = astar(cost, (2, 0), (2, 8))
    assert not np.any(cost[first[1:-1, 0], first[1:-1, 1]] > 1.0)
    np.testing.assert_array_equal(first, astar(cost, (2, 0), (2, 8)))


def test_path_from_tree_root_and_unreachable():
    cost = np.ones((3, 3), dtype=np.float32)
    cost[:, 1] = np.inf
    _, parent = shortest_path_tree(cost, (0, 0))
    assert path_from_tree(parent, (0, 2)) is None
    assert path_from_tree(parent, (0, 0)) is None  # root without `start`: ambiguous
    np.testing.assert_array_equal(path_from_tree(parent, (0, 0), (0, 0)), [[0, 0]])


@pytest.mark.parametrize(
    "cost, cell",
    [
        (np.full((3, 3), np.nan, dtype=np.float32), (0, 0)),
        (np.zeros((3, 3), dtype=np.float32), (0, 0)),
        (np.ones(9, dtype=np.float32), (0, 0)),
        (np.ones((3, 3), dtype=np.float32), (3, 0)),
        (np.ones((3, 3), dtype=np.float32), (0, -1)),
    ],
)
def test_bad_input_raises(cost, cell):
    with pytest.raises(SearchError):
        astar(cost, cell, (0, 0))


def test_astar_agrees_with_tree_on_a_kth_map(kth_dev_dir):
    raw = np.load(kth_dev_dir / "50015848" / "occ_map.npy")
    walls = raw[: raw.shape[0] // 2 * 2, : raw.shape[1] // 2 * 2] == 0
    walls = walls.reshape(walls.shape[0] // 2, 2, walls.shape[1] // 2, 2).any(axis=(1, 3))
    cost = np.where(walls, np.inf, 1.0).astype(np.float32)
    free = np.argwhere(~walls)
    start = tuple(free[0])
    dist, parent = shortest_path_tree(cost, start)
    reachable = np.argwhere(np.isfinite(dist))
    goal = tuple(reachable[np.argmax(dist[np.isfinite(dist)])])
    path = astar(cost, start, goal)
    assert_valid_path(cost, path, start, goal)
    assert path_cost(cost, path) == pytest.approx(float(dist[goal]), rel=1e-5)
    np.testing.assert_array_equal(reachable_mask(cost, start), np.isfinite(dist))
