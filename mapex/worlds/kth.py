"""Load a KTH floor-plan directory (the authors' `kth_test_maps/<id>/` format,
docs/algorithms.md#worlds).

A directory holds `occ_map.npy` (uint8, 0 = wall, 254 = free, 0.05 m per cell) and
`valid_space.npy` (uint8 room labels, only `label > 0` matters) of the same 2-D shape.
Both are downsampled 2x to the project's 0.1 m cells: a block is a wall when any of its
four cells is one (block *min* of the codes, odd edges padded with wall) and valid when
any of them is (block *max*, padded with 0). Bad files raise a one-line `WorldError`
naming the file; each array's header is checked (dtype, shape, the data the file holds and
the `world.max_cells` limit) before its data is read (`mapex.io_limits`), so a forged
header costs nothing.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mapex.config import WorldConfig
from mapex.io_limits import read_npy
from mapex.worlds.base import World, WorldError, one_line

OCCUPANCY_FILE = "occ_map.npy"
VALID_SPACE_FILE = "valid_space.npy"
KTH_WALL = 0
KTH_FREE = 254
MAX_VALUES_SHOWN = 5  # offending values quoted in an error message
CELLS_PER_WORLD_CELL = 4  # a 0.1 m world cell is 2 x 2 cells of 0.05 m


def load_kth_map(directory: str | Path, max_cells: int = WorldConfig().max_cells) -> World:
    """The KTH map in `directory` at 0.1 m per cell, named after the directory; a one-line
    WorldError when a file is bad or the world would have more than `max_cells` cells."""
    directory = Path(directory)
    if not directory.is_dir():
        raise WorldError(f"no such map directory: {directory}")
    occupancy_path = directory / OCCUPANCY_FILE
    valid_path = directory / VALID_SPACE_FILE
    codes = _load_uint8_map(occupancy_path, max_cells)
    labels = _load_uint8_map(valid_path, max_cells)
    _check_wall_codes(codes, occupancy_path)
    if codes.shape != labels.shape:
        raise WorldError(
            f"{occupancy_path} {codes.shape} and {valid_path} {labels.shape} differ in shape"
        )
    valid_space = downsample_2x(labels > 0, pad_value=False)
    if not valid_space.any():
        raise WorldError(f"{valid_path}: no valid space (every label is 0)")
    walls = downsample_2x(codes == KTH_WALL, pad_value=True)
    return World(Path(os.path.abspath(directory)).name, walls, valid_space)


def downsample_2x(mask: np.ndarray, pad_value: bool) -> np.ndarray:
    """Halve a bool map: a 2x2 block is True when any cell is; odd edges padded with `pad_value`.

    On walls this is the block *min* of the KTH codes, on valid space the block *max*.
    """
    rows, cols = mask.shape
    padded = np.pad(mask, ((0, rows % 2), (0, cols % 2)), constant_values=pad_value)
    blocks = padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2)
    return blocks.any(axis=(1, 3))


def _load_uint8_map(path: Path, max_cells: int) -> np.ndarray:
    """A 2-D uint8 array from the .npy file at `path` whose world (2x downsampled) fits in
    `max_cells`, or a one-line WorldError naming it; judged by its header before any data
    is read."""
    if not path.exists():
        raise WorldError(f"missing map file: {path}")
    hint = f"at 0.05 m, {CELLS_PER_WORLD_CELL} x world.max_cells; --set world.max_cells=N raises it"
    try:
        return read_npy(path, np.uint8, 2, CELLS_PER_WORLD_CELL * max_cells, "map", hint)
    except (ValueError, OSError, EOFError) as error:
        raise WorldError(one_line(error)) from None


def _check_wall_codes(codes: np.ndarray, path: Path) -> None:
    """Reject occupancy codes other than 0 (wall) and 254 (free)."""
    bad = (codes != KTH_WALL) & (codes != KTH_FREE)
    if bad.any():
        shown = np.unique(codes[bad])[:MAX_VALUES_SHOWN].tolist()
        raise WorldError(f"{path}: values {shown} besides {KTH_WALL} (wall) and {KTH_FREE} (free)")
