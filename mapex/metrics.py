"""Run metrics of docs/algorithms.md#metrics: coverage, occupied-class IoU, topological
understanding, AUC, and a robot's idle steps."""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import cv2
import numpy as np
from numba import njit

from mapex.grid import OCCUPIED, UNKNOWN, Cell
from mapex.search import shortest_path_tree


class MetricsError(ValueError):
    """Input a metric cannot be computed on; the message names the cause."""


def coverage(observed: np.ndarray, valid_space: np.ndarray) -> float:
    """Known cells inside valid space / valid-space cells."""
    n_valid = int(np.count_nonzero(valid_space))
    if n_valid == 0:
        raise MetricsError("coverage needs a non-empty valid space")
    return np.count_nonzero((observed != UNKNOWN) & valid_space) / n_valid


def building_footprint(valid_space: np.ndarray, margin_cells: int) -> np.ndarray:
    """Valid space grown by a Euclidean disc of radius `margin_cells`, so that the walls
    bounding the rooms are inside (bool)."""
    if margin_cells < 0:
        raise MetricsError(f"margin_cells must be >= 0, got {margin_cells}")
    offsets = np.arange(-margin_cells, margin_cells + 1)
    disc = (offsets[:, None] ** 2 + offsets[None, :] ** 2 <= margin_cells**2).astype(np.uint8)
    return cv2.dilate(np.asarray(valid_space, dtype=np.uint8), disc).astype(bool)


def predicted_occupancy(
    observed: np.ndarray, main_prediction: np.ndarray, threshold: float
) -> np.ndarray:
    """Thresholded P_t (bool, True = occupied): known cells from O_t, unknown cells True
    where the main prediction is >= threshold."""
    if observed.shape != main_prediction.shape:
        raise MetricsError(
            f"observed {observed.shape} and prediction {main_prediction.shape} shapes differ"
        )
    return np.where(observed == UNKNOWN, main_prediction >= threshold, observed == OCCUPIED)


def occupied_iou(
    predicted_occupied: np.ndarray, true_occupied: np.ndarray, footprint: np.ndarray
) -> float:
    """IoU of the occupied class inside `footprint`; 1.0 when the union is empty."""
    predicted = predicted_occupied & footprint
    truth = true_occupied & footprint
    union = int(np.count_nonzero(predicted | truth))
    if union == 0:
        return 1.0
    return np.count_nonzero(predicted & truth) / union


def tu_goals(
    world_name: str,
    true_occupied: np.ndarray,
    valid_space: np.ndarray,
    start: Cell,
    n_goals: int,
) -> np.ndarray:
    """TU goals, int64 (n, 2): drawn uniformly without replacement from the free valid cells
    of the ground truth (all of them when fewer than `n_goals`), with a seed fixed per
    (map, start): crc32 of "name:row,col", stable across processes."""
    candidates = np.flatnonzero(valid_space & ~true_occupied)
    if candidates.size == 0:
        raise MetricsError(f"world '{world_name}' has no free valid cell to draw TU goals from")
    seed = zlib.crc32(f"{world_name}:{int(start[0])},{int(start[1])}".encode())
    rng = np.random.default_rng(seed)
    chosen = rng.choice(candidates, size=min(n_goals, candidates.size), replace=False)
    return np.stack(np.unravel_index(chosen, valid_space.shape), axis=1)


def topological_understanding(
    predicted_occupied: np.ndarray, true_occupied: np.ndarray, start: Cell, goals: np.ndarray
) -> float:
    """Fraction of goals whose shortest path on the predicted map exists and crosses no
    ground-truth wall.

    Paths: 8-connected, unit cell cost, no corner cutting (as `mapex.search`),
    predicted-occupied cells blocked except the start. One shortest-path tree from the
    start serves all goals.
    """
    goals = np.asarray(goals).reshape(-1, 2)
    if goals.shape[0] == 0:
        raise MetricsError("topological understanding needs at least one goal")
    cost = np.where(predicted_occupied, np.float32(np.inf), np.float32(1.0)).astype(np.float32)
    _, parent = shortest_path_tree(cost, start)
    clean = _clean_path_flags(
        parent.ravel(),
        np.ascontiguousarray(true_occupied, dtype=np.bool_).ravel(),
        np.ravel_multi_index((goals[:, 0], goals[:, 1]), cost.shape).astype(np.int64),
        int(start[0]) * cost.shape[1] + int(start[1]),
    )
    return float(clean.mean())


_UNVISITED, _CLEAN, _DIRTY = 0, 1, 2


@njit(cache=True)
def _clean_path_flags(parent, wall, goals, start_flat):
    """Per goal: reachable in the tree and no ground-truth wall on its path (memoised walk)."""
    state = np.zeros(parent.size, dtype=np.int8)
    chain = np.empty(parent.size, dtype=np.int64)
    result = np.zeros(goals.size, dtype=np.bool_)
    for i in range(goals.size):
        length = 0
        node = goals[i]
        while state[node] == _UNVISITED and parent[node] >= 0:
            chain[length] = node
            length += 1
            node = parent[node]
        if state[node] == _UNVISITED:  # a root: the start, or an unreachable cell
            state[node] = _CLEAN if node == start_flat and not wall[node] else _DIRTY
        for j in range(length - 1, -1, -1):
            above = state[parent[chain[j]]]
            state[chain[j]] = _CLEAN if above == _CLEAN and not wall[chain[j]] else _DIRTY
        result[i] = state[goals[i]] == _CLEAN
    return result


def idle_steps(trajectory: np.ndarray) -> int:
    """The steps of a trajectory (int (n + 1, 2): the pose before the first step, then after
    each) at which the robot did not move: it stood still while the run went on."""
    poses = np.asarray(trajectory).reshape(-1, 2)
    return int(np.count_nonzero((poses[1:] == poses[:-1]).all(axis=1)))


def curve_auc(values: Sequence[float] | np.ndarray) -> float:
    """Area under a sampled metric curve: its mean over the samples (docs/algorithms.md#metrics)."""
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        raise MetricsError("curve_auc needs at least one sample")
    return float(values.mean())
