"""Cell conventions shared by every module.

One grid cell is `RESOLUTION_M` metres. Cells are addressed as (row, col) integers.

* Ground truth (`World.occupancy`): bool array, True = wall.
* Observed map O_t: uint8 codes `FREE`, `UNKNOWN`, `OCCUPIED` chosen so that
  `code / 2` is the paper's occupancy value (0, 0.5, 1).
* Probability maps (predictions, mean, variance): float32 in [0, 1].
"""

from __future__ import annotations

import numpy as np

RESOLUTION_M = 0.1

FREE = np.uint8(0)
UNKNOWN = np.uint8(1)
OCCUPIED = np.uint8(2)

Cell = tuple[int, int]


def new_observed_map(shape: tuple[int, int]) -> np.ndarray:
    """An all-unknown observed map of `shape` (rows, cols)."""
    return np.full(shape, UNKNOWN, dtype=np.uint8)


def observed_to_probability(observed: np.ndarray) -> np.ndarray:
    """Observed codes -> float32 occupancy (free 0, unknown 0.5, occupied 1)."""
    return observed.astype(np.float32) * np.float32(0.5)


def metres_to_cells(distance_m: float) -> int:
    """Round a distance in metres to whole cells."""
    return int(round(distance_m / RESOLUTION_M))
