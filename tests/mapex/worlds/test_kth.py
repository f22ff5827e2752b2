"""KTH map loading: validation, 2x downsampling, the development maps."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from mapex.worlds import World, WorldError, load_kth_map, load_world
from mapex.worlds.kth import OCCUPANCY_FILE, VALID_SPACE_FILE, downsample_2x

WALL, FREE = 0, 254


def write_map(directory: Path, occupancy: np.ndarray, valid: np.ndarray) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    np.save(directory / OCCUPANCY_FILE, occupancy)
    np.save(directory / VALID_SPACE_FILE, valid)
    return directory


def free_map(shape: tuple[int, int]) -> np.ndarray:
    return np.full(shape, FREE, dtype=np.uint8)


def brute_force_downsample(mask: np.ndarray, pad_value: bool) -> np.ndarray:
    rows, cols = (mask.shape[0] + 1) // 2, (mask.shape[1] + 1) // 2
    out = np.zeros((rows, cols), dtype=bool)
    for r in range(rows):
        for c in range(cols):
            cells = [
                mask[y, x] if y < mask.shape[0] and x < mask.shape[1] else pad_value
                for y in (2 * r, 2 * r + 1)
                for x in (2 * c, 2 * c + 1)
            ]
            out[r, c] = any(cells)
    return out


@pytest.mark.parametrize("shape", [(1, 1), (2, 2), (3, 5), (4, 7), (6, 4), (9, 9)])
@pytest.mark.parametrize("pad_value", [False, True])
def test_downsample_matches_brute_force(shape: tuple[int, int], pad_value: bool) -> None:
    mask = np.random.default_rng(sum(shape)).random(shape) < 0.2
    np.testing.assert_array_equal(
        downsample_2x(mask, pad_value), brute_force_downsample(mask, pad_value)
    )


def test_load_downsamples_walls_by_block_min_and_valid_by_block_max(tmp_path: Path) -> None:
    occupancy = free_map((3, 5))
    occupancy[0, 1] = WALL  # one wall cell walls its whole block
    valid = np.zeros((3, 5), dtype=np.uint8)
    valid[2, 2] = 7  # any label > 0 in a block makes it valid
    world = load_kth_map(write_map(tmp_path / "m", occupancy, valid))
    # the odd last row and column are padded with wall
    expected_walls = np.array([[True, False, True], [True, True, True]])
    expected_valid = np.array([[False, False, False], [False, True, False]])
    np.testing.assert_array_equal(world.occupancy, expected_walls)
    np.testing.assert_array_equal(world.valid_space, expected_valid)
    assert world.occupancy.dtype == bool and world.valid_space.dtype == bool


def test_even_free_map_has_no_walls_and_is_named_after_directory(tmp_path: Path) -> None:
    world = load_kth_map(write_map(tmp_path / "50010101", free_map((4, 6)), np.ones((4, 6), "u1")))
    assert world.name == "50010101"
    assert world.shape == (2, 3)
    assert not world.occupancy.any()
    assert world.valid_space.all()


def _pickle_file(path: Path) -> None:
    path.write_bytes(pickle.dumps(free_map((4, 4))))


def _object_array(path: Path) -> None:
    np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)


def _npz_archive(path: Path) -> None:
    with path.open("wb") as handle:
        np.savez(handle, occ=free_map((4, 4)))


def _corrupt(path: Path) -> None:
    path.write_bytes(b"\x93NUMPY garbage" + bytes(range(40)))


def _truncated(path: Path) -> None:
    np.save(path, free_map((40, 40)))
    path.write_bytes(path.read_bytes()[:200])


@pytest.mark.parametrize(
    "spoil, expected",
    [
        (_pickle_file, "not a loadable .npy file"),
        (_object_array, "not a loadable .npy file"),
        (_npz_archive, "not a .npy array file"),
        (_corrupt, "not a loadable .npy file"),
        (_truncated, "the file holds 72 bytes of data"),
        (lambda p: np.save(p, np.full((4, 4), 254.0)), "dtype float64"),
        (lambda p: np.save(p, np.full((4, 4), 254, dtype=np.int16)), "dtype int16"),
        (lambda p: np.save(p, np.full((2, 4, 4), 254, dtype=np.uint8)), "expected a 2-D map"),
        (lambda p: np.save(p, np.full(16, 254, dtype=np.uint8)), "expected a 2-D map"),
        (lambda p: p.unlink(), "missing map file"),
    ],
)
@pytest.mark.parametrize("file_name", [OCCUPANCY_FILE, VALID_SPACE_FILE])
def test_bad_file_gives_one_line_error_naming_it(
    tmp_path: Path, spoil, expected: str, file_name: str
) -> None:
    directory = write_map(tmp_path / "m", free_map((4, 4)), np.ones((4, 4), np.uint8))
    spoil(directory / file_name)
    with pytest.raises(WorldError) as caught:
        load_kth_map(directory)
    message = str(caught.value)
    assert expected in message
    assert str(directory / file_name) in message
    assert "\n" not in message


def test_other_occupancy_values_are_rejected(tmp_path: Path) -> None:
    occupancy = free_map((4, 4))
    occupancy[1, 1], occupancy[2, 2] = 128, 255
    directory = write_map(tmp_path / "m", occupancy, np.ones((4, 4), np.uint8))
    with pytest.raises(WorldError, match=r"occ_map\.npy: values \[128, 255\]") as caught:
        load_kth_map(directory)
    assert "\n" not in str(caught.value)


def test_shape_mismatch_names_both_files(tmp_path: Path) -> None:
    directory = write_map(tmp_path / "m", free_map((4, 4)), np.ones((4, 6), np.uint8))
    with pytest.raises(WorldError, match="differ in shape") as caught:
        load_kth_map(directory)
    assert OCCUPANCY_FILE in str(caught.value) and VALID_SPACE_FILE in str(caught.value)


def test_empty_valid_space_is_rejected(tmp_path: Path) -> None:
    directory = write_map(tmp_path / "m", free_map((4, 4)), np.zeros((4, 4), np.uint8))
    with pytest.raises(WorldError, match=r"valid_space\.npy: no valid space"):
        load_kth_map(directory)


def test_missing_directory(tmp_path: Path) -> None:
    with pytest.raises(WorldError, match="no such map directory: .*nowhere"):
        load_kth_map(tmp_path / "nowhere")


def test_load_world_dispatches_on_the_spec(tmp_path: Path) -> None:
    directory = write_map(tmp_path / "plan7", free_map((4, 4)), np.ones((4, 4), np.uint8))
    assert load_world(str(directory)).name == "plan7"
    assert load_world("generated:2").name == "generated:2"
    default = load_world("default")
    assert isinstance(default, World) and default.name == "generated:0"


@pytest.mark.parametrize(
    "spec, expected",
    [
        ("generated:abc", "bad generated seed 'abc'"),
        ("generated:-3", "bad generated seed '-3'"),
        ("generated:", "bad generated seed ''"),
        ("generated-open:1.5", "bad generated seed '1.5'"),
        ("no/such/dir", "no such map directory: no/such/dir"),
        ("", "empty world spec"),
    ],
)
def test_load_world_rejects_bad_specs(spec: str, expected: str) -> None:
    with pytest.raises(WorldError) as caught:
        load_world(spec)
    assert expected in str(caught.value) and "\n" not in str(caught.value)


DEV_MAP_SHAPES = {
    "50015847": (442, 1327),  # 883 x 2653 at 0.05 m
    "50015848": (440, 1321),
    "50037764_PLAN1": (211, 1354),
    "50052748": (218, 429),
}


@pytest.mark.parametrize("map_id, shape", sorted(DEV_MAP_SHAPES.items()))
def test_dev_maps_load_at_a_tenth_of_a_metre(kth_dev_dir: Path, map_id: str, shape) -> None:
    world = load_kth_map(kth_dev_dir / map_id)
    assert world.name == map_id
    assert world.shape == shape
    assert world.resolution_m == pytest.approx(0.1)
    # walls are a minority of the map, and most of the valid space is free
    assert 0.02 < world.occupancy.mean() < 0.3
    assert (world.valid_space & ~world.occupancy).sum() > 0.8 * world.valid_space.sum()
