"""Load a KTH floor-plan directory (the authors' `kth_test_maps/<id>/` format,
docs/algorithms.md#worlds).

A directory holds `occ_map.npy` (uint8, 0 = wall, 254 = free, 0.05 m per cell) and
`valid_space.npy` (uint8 room labels, only `label > 0` matters) of the same 2-D shape.
Both are downsampled 2x to the project's 0.1 m cells: a block is a wall when any of its
four cells is one (block *min* of the codes, odd edges padded with wall) and valid when
any of them is (block *max*, padded with 0). Bad files raise a one-line `WorldError`
naming the file.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from mapex.worlds.base import World, WorldError, one_line

OCCUPANCY_FILE = "occ_map.npy"
VALID_SPACE_FILE = "valid_space.npy"
KTH_WALL = 0
KTH_FREE = 254
MAX_VALUES_SHOWN = 5  # offending values quoted in an error message


def load_kth_map(directory: str | Path) -> World:
    """The KTH map in `directory` at 0.1 m per cell, named after the directory."""
    directory = Path(directory)
    if not directory.is_dir():
        raise WorldError(f"no such map directory: {directory}")
    occupancy_path = directory / OCCUPANCY_FILE
    valid_path = directory / VALID_SPACE_FILE
    codes = _load_uint8_map(occupancy_path)
    labels = _load_uint8_map(valid_path)
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


def _load_uint8_map(path: Path) -> np.ndarray:
    """A 2-D uint8 array from the .npy file at `path`, or a one-line WorldError naming it."""
    if not path.is_file():
        raise WorldError(f"missing map file: {path}")
    try:
        loaded = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as error:
        raise WorldError(f"not a loadable .npy file: {path} ({one_line(error)})") from None
    if not isinstance(loaded, np.ndarray):
        loaded.close()  # an .npz archive
        raise WorldError(f"not a .npy array file: {path}")
    if loaded.dtype != np.uint8:
        raise WorldError(f"{path}: dtype {loaded.dtype}, expected uint8")
    if loaded.ndim != 2:
        raise WorldError(f"{path}: shape {loaded.shape}, expected a 2-D map")
    return loaded


def _check_wall_codes(codes: np.ndarray, path: Path) -> None:
    """Reject occupancy codes other than 0 (wall) and 254 (free)."""
    bad = (codes != KTH_WALL) & (codes != KTH_FREE)
    if bad.any():
        shown = np.unique(codes[bad])[:MAX_VALUES_SHOWN].tolist()
        raise WorldError(f"{path}: values {shown} besides {KTH_WALL} (wall) and {KTH_FREE} (free)")
