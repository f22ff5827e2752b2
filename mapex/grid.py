"""Cell conventions shared by every module.

One grid cell is `RESOLUTION_M` metres. Cells are addressed as (row, col) integers.

* Ground truth (`World.occupancy`): bool array, True = wall.
* Observed map O_t: uint8 codes `FREE`, `UNKNOWN`, `OCCUPIED` chosen so that
  `code / 2` is the paper's occupancy value (0, 0.5, 1).
* Probability maps (predictions, mean, variance): float32 in [0, 1]. Predictor outputs
  are quantised to uint8 levels q / 255 (`quantise_probability`), in one process as on
  the wire, so an in-process run and a distributed one see the very same numbers.
"""

from __future__ import annotations

import numpy as np

RESOLUTION_M = 0.1
QUANTISATION_LEVELS = 255  # uint8 probability q stands for q / 255

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


def quantise_probability(probability: np.ndarray) -> np.ndarray:
    """Probabilities in [0, 1] (any float array) -> uint8 round(p * 255).

    `dequantise_probability` brings them back within 1/510 (half a level). Values outside
    [0, 1] or not finite raise ValueError: they are a bug upstream, not noise to clip.
    """
    values = np.asarray(probability, dtype=np.float32)
    if values.size and not (np.isfinite(values).all() and values.min() >= 0 and values.max() <= 1):
        raise ValueError("probabilities to quantise must be finite and within [0, 1]")
    return np.rint(values * np.float32(QUANTISATION_LEVELS)).astype(np.uint8)


def dequantise_probability(quantised: np.ndarray) -> np.ndarray:
    """uint8 levels of `quantise_probability` -> float32 probabilities q / 255."""
    if quantised.dtype != np.uint8:
        raise ValueError(f"quantised probabilities must be uint8, got {quantised.dtype}")
    return quantised.astype(np.float32) / np.float32(QUANTISATION_LEVELS)
