"""Reading user-named files within limits (issue #53, defects 6 and 7): no file is read
that is not a regular file or larger than the limit, and an array is judged by its header
(shape and dtype against the file's size and the cell limit) before its data is read."""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mapex.io_limits import FileLimitError, check_npz, read_bytes, read_npy, read_text
from mapex.report.runs import ReportError, load_run, load_snapshots
from mapex.worlds import WorldError, load_kth_map, load_world

FORGED_SHAPE = (200_000, 200_000)  # 40 GB of uint8: reading it would end in a MemoryError


def forged_npy(path: Path, shape: tuple[int, ...] = FORGED_SHAPE, dtype: str = "|u1") -> Path:
    """A .npy file whose header claims `shape` but that holds 16 bytes of data."""
    with path.open("wb") as handle:
        np.lib.format.write_array_header_1_0(
            handle, {"descr": dtype, "fortran_order": False, "shape": shape}
        )
        handle.write(bytes(16))
    return path


def forged_npz(path: Path, member_shape: tuple[int, ...] = FORGED_SHAPE) -> Path:
    """An .npz archive whose `observed` member's header claims `member_shape`."""
    member = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        member, {"descr": "|u1", "fortran_order": False, "shape": member_shape}
    )
    member.write(bytes(16))
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("observed.npy", member.getvalue())
        archive.writestr("steps.npy", _npy_bytes(np.array([200])))
    return path


def _npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: Path("/dev/zero"), "not a regular file (a character device)"),
        (lambda d: fifo(d / "pipe"), "not a regular file (a FIFO)"),
        (lambda d: d, "not a regular file (a directory)"),
        (lambda d: _write(d / "big", b"x" * 101), "holds 101 bytes, above the limit of 100"),
    ],
    ids=["dev-zero", "fifo", "directory", "too-big"],
)
def test_only_regular_files_within_the_limit_are_read(tmp_path, make, message):
    path = make(tmp_path)
    for read in (read_bytes, read_text):
        with pytest.raises(FileLimitError, match=message.replace("(", r"\(").replace(")", r"\)")):
            read(path, 100)  # returns at once: neither /dev/zero nor a FIFO is ever read
    assert read_text(_write(tmp_path / "ok", b"x" * 100), 100) == "x" * 100


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def test_a_forged_npy_header_is_refused_before_any_data_is_read(tmp_path):
    path = forged_npy(tmp_path / "forged.npy")
    with pytest.raises(FileLimitError, match="holds 16 bytes of data") as caught:
        read_npy(path, np.uint8, 2, 10**12)
    assert "(200000, 200000)" in str(caught.value) and "\n" not in str(caught.value)
    with pytest.raises(FileLimitError, match="above the limit of 1,000"):
        read_npy(path, np.uint8, 2, 1_000)  # the cell limit, from the header alone
    with pytest.raises(ValueError, match="dtype float64, expected uint8"):
        read_npy(forged_npy(tmp_path / "f8.npy", dtype="<f8"), np.uint8, 2, 10**12)


def test_an_npz_is_judged_by_its_members_headers(tmp_path):
    with pytest.raises(FileLimitError, match="observed.npy: its header claims shape"):
        check_npz(forged_npz(tmp_path / "forged.npz"))
    good = tmp_path / "good.npz"
    np.savez_compressed(good, steps=np.array([200]), observed=np.zeros((1, 30, 40), np.uint8))
    assert check_npz(good)["observed"][0] == (1, 30, 40)
    with pytest.raises(FileLimitError, match="would unpack to"):
        check_npz(good, max_bytes=len(good.read_bytes()) + 10)  # small on disk, not unpacked
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(ValueError, match="not a loadable .npz file"):
        check_npz(tmp_path / "bad.npz")


def test_a_map_with_a_forged_header_is_a_one_line_world_error(tmp_path):
    directory = tmp_path / "forged"
    directory.mkdir()
    forged_npy(directory / "occ_map.npy")
    np.save(directory / "valid_space.npy", np.ones((4, 4), np.uint8))
    for load in (load_kth_map, load_world):
        with pytest.raises(WorldError, match="occ_map.npy: its map of shape") as caught:
            load(str(directory))  # above 4 x world.max_cells, from the header alone
        assert "world.max_cells" in str(caught.value) and "\n" not in str(caught.value)
    with pytest.raises(WorldError, match="holds 16 bytes of data"):
        load_kth_map(directory, max_cells=10**11)  # a limit that allows it: the size refuses


def test_a_map_above_max_cells_is_refused_from_its_header(tmp_path):
    directory = tmp_path / "m"
    directory.mkdir()
    np.save(directory / "occ_map.npy", np.full((39, 39), 254, np.uint8))
    np.save(directory / "valid_space.npy", np.ones((39, 39), np.uint8))
    assert load_world(str(directory), max_cells=400).shape == (20, 20)
    with pytest.raises(WorldError, match="1,521 cells, above the limit of 396"):
        load_kth_map(directory, max_cells=99)  # 1,521 cells at 0.05 m > 4 x 99: never read
    with pytest.raises(WorldError, match="has 400 cells .* above the limit of 399"):
        load_world(str(directory), max_cells=399)  # read (1,521 <= 4 x 399), then refused


def test_map_files_that_are_not_regular_files_are_refused(tmp_path):
    directory = tmp_path / "m"
    directory.mkdir()
    fifo(directory / "occ_map.npy")
    (directory / "valid_space.npy").symlink_to("/dev/zero")
    with pytest.raises(WorldError, match="not a regular file"):
        load_kth_map(directory)
    os.unlink(directory / "occ_map.npy")
    np.save(directory / "occ_map.npy", np.full((4, 4), 254, np.uint8))
    with pytest.raises(WorldError, match="valid_space.npy is not a regular file"):
        load_kth_map(directory)


def test_run_folders_are_read_within_limits(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "metrics.json").symlink_to("/dev/zero")
    with pytest.raises(OSError, match="not a regular file"):
        load_run(folder)
    (folder / "metrics.json").unlink()
    (folder / "metrics.json").write_text(
        '{"world": "w", "method": "nearest", "start_index": 0, "auc": {}}'
    )
    fifo(folder / "curves.csv")
    with pytest.raises(OSError, match="curves.csv is not a regular file"):
        load_run(folder)
    (folder / "curves.csv").unlink()
    (folder / "curves.csv").write_text("step,coverage,iou,tu\n0,0.1,0.2,\n50,0.3\n")
    with pytest.raises(ReportError, match="line 3 does not have 4 fields"):
        load_run(folder)
    (folder / "curves.csv").write_text("step,coverage,iou,tu\n0,0.1,0.2,\n50,0.3,0.4,0.5\n")
    run = load_run(folder)
    assert run.steps.tolist() == [0, 50]
    forged_npz(folder / "snapshots.npz")
    with pytest.raises(FileLimitError, match="its header claims shape"):
        load_snapshots(run)
