"""Reading the files a user names, within limits (docs/design.md#trust).

Every file the project reads from a path given on a command line or found in a folder it
was pointed at (a starts file, a map directory's arrays, a run folder's metrics, curves
and snapshots) goes through here: it must be a regular file (not /dev/zero, a FIFO or a
directory), no larger than a limit from the configuration (`world.max_file_bytes`, or
`world.max_cells` for map arrays), and a `.npy` array (also inside an `.npz` archive) is
judged by its header, shape and dtype against the file's size and the limit, before any of
its data is read. Anything else is a one-line `FileLimitError` (an OSError, so every
command's handler of unreadable files reports it as it does a missing file).
"""

from __future__ import annotations

import io
import math
import os
import stat
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from mapex.config import WorldConfig

DEFAULT_MAX_BYTES = WorldConfig().max_file_bytes


class FileLimitError(OSError):
    """A file that is not a regular file, or larger than what may be read; one line."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "file refused"


MAX_FILE_BYTES_HINT = "--set world.max_file_bytes=N raises it"


def open_regular(
    path: str | Path, max_bytes: int | None = DEFAULT_MAX_BYTES, hint: str = MAX_FILE_BYTES_HINT
) -> BinaryIO:
    """`path` opened for binary reading, once it is known to be a regular file of at most
    `max_bytes` bytes (None: any size; FileLimitError otherwise, with `hint` saying how to
    raise the limit; OSError when it cannot be opened).

    The file is opened without blocking (a FIFO does not wait for a writer) and judged by
    the descriptor's own `fstat`, so what is checked is what is read."""
    descriptor = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            raise FileLimitError(f"{path} is not a regular file ({_kind(status.st_mode)})")
        if max_bytes is not None and status.st_size > max_bytes:
            raise FileLimitError(
                f"{path} holds {status.st_size:,} bytes, above the limit of {max_bytes:,} ({hint})"
            )
        if hasattr(os, "set_blocking"):
            os.set_blocking(descriptor, True)
        return os.fdopen(descriptor, "rb")
    except BaseException:
        os.close(descriptor)
        raise


def read_bytes(path: str | Path, max_bytes: int = DEFAULT_MAX_BYTES) -> bytes:
    """The whole of a regular file of at most `max_bytes` bytes (see `open_regular`); a
    file that grew past the limit while being read is refused too."""
    with open_regular(path, max_bytes) as handle:
        data = handle.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise FileLimitError(f"{path} grew above the limit of {max_bytes:,} bytes while read")
    return data


def read_text(path: str | Path, max_bytes: int = DEFAULT_MAX_BYTES) -> str:
    """A regular UTF-8 text file of at most `max_bytes` bytes (UnicodeDecodeError, a
    ValueError, when it is not UTF-8)."""
    return read_bytes(path, max_bytes).decode("utf-8")


def read_npy(
    path: str | Path,
    dtype: np.dtype | type,
    ndim: int,
    max_items: int,
    what: str = "array",
    hint: str = "",
) -> np.ndarray:
    """The `.npy` array at `path`, once its header says it is a `dtype` array of `ndim`
    dimensions with at most `max_items` items (`hint`: how to raise that limit) whose data
    the file actually holds (FileLimitError / ValueError, one line naming the file,
    otherwise; no data is read before). Bytes after the data are never read."""
    with open_regular(path, None) as handle:
        size = os.fstat(handle.fileno()).st_size
        shape = check_npy_header(handle, size, dtype, ndim, max_items, f"{path}", what, hint)
        handle.seek(0)
        array = np.lib.format.read_array(handle, allow_pickle=False)
    if array.shape != shape:  # the file changed while being read
        raise ValueError(f"{path}: holds {array.shape}, its header said {shape}")
    return array


def check_npz(
    path: str | Path,
    max_bytes: int = DEFAULT_MAX_BYTES,
    what: str = "archive",
    hint: str = MAX_FILE_BYTES_HINT,
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """{member name without .npy: (shape, dtype)} of the `.npz` archive at `path`, read from
    the members' headers through zipfile: a regular file of at most `max_bytes`, whose
    members' data add up to at most `max_bytes` uncompressed and each hold what their
    header claims (FileLimitError / ValueError, one line, otherwise). Reading the arrays
    after this check (`np.load`) reads no more than that."""
    with open_regular(path, max_bytes, hint) as handle:
        try:
            with zipfile.ZipFile(handle) as archive:
                return _check_members(archive, path, max_bytes, what, hint)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError) as error:
            raise ValueError(f"not a loadable .npz file: {path} ({_one_line(error)})") from None


def _check_members(
    archive: zipfile.ZipFile, path: str | Path, max_bytes: int, what: str, hint: str
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    members = archive.infolist()
    total = sum(member.file_size for member in members)
    if total > max_bytes:
        raise FileLimitError(
            f"{path}: its {what} would unpack to {total:,} bytes, above the limit of "
            f"{max_bytes:,} ({hint})"
        )
    found = {}
    for member in members:
        name = f"{path}:{member.filename}"
        with archive.open(member) as stream:
            header = io.BytesIO(stream.read(_HEADER_ROOM))
        shape, dtype = _npy_header(header, name)
        _check_holds(shape, dtype, member.file_size - header.tell(), name)
        found[member.filename.removesuffix(".npy")] = (shape, dtype)
    return found


def check_npy_header(
    handle: BinaryIO,
    size: int,
    dtype: np.dtype | type,
    ndim: int,
    max_items: int,
    name: str,
    what: str = "array",
    hint: str = "",
) -> tuple[int, ...]:
    """The shape in the `.npy` header at `handle`'s position, once it is a `dtype` array of
    `ndim` dimensions, of at most `max_items` items (`hint`: how to raise that limit), whose
    data fits in the `size`-byte file (ValueError / FileLimitError, one line naming `name`)."""
    shape, found = _npy_header(handle, name)
    if found != np.dtype(dtype):
        raise ValueError(f"{name}: dtype {found}, expected {np.dtype(dtype)}")
    if len(shape) != ndim:
        raise ValueError(f"{name}: shape {shape}, expected a {ndim}-D {what}")
    items = math.prod(shape)
    if items > max_items:
        raise FileLimitError(
            f"{name}: its {what} of shape {shape} has {items:,} cells, above the limit of "
            f"{max_items:,}" + (f" ({hint})" if hint else "")
        )
    _check_holds(shape, found, size - handle.tell(), name)
    return shape


_HEADER_ROOM = 65_536  # the longest .npy header read (numpy writes a few hundred bytes)
_ZIP_MAGIC = b"PK\x03\x04"  # an .npz archive where a .npy file belongs


def _npy_header(handle: BinaryIO, name: str) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from a `.npy` header (format 1.0 or 2.0); ValueError naming `name`."""
    start = handle.tell()
    if handle.read(len(_ZIP_MAGIC)) == _ZIP_MAGIC:
        raise ValueError(f"not a .npy array file: {name} (an .npz archive)")
    handle.seek(start)
    try:
        version = np.lib.format.read_magic(handle)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(
                handle, max_header_size=_HEADER_ROOM
            )
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(
                handle, max_header_size=_HEADER_ROOM
            )
        else:
            raise ValueError(f"format version {version[0]}.{version[1]} is not read")
    except (ValueError, EOFError, SyntaxError, TypeError) as error:
        raise ValueError(f"not a loadable .npy file: {name} ({_one_line(error)})") from None
    if dtype.hasobject:
        raise ValueError(f"not a loadable .npy file: {name} (an object array: never unpickled)")
    return tuple(int(n) for n in shape), dtype


def _check_holds(shape: tuple[int, ...], dtype: np.dtype, data_bytes: int, name: str) -> None:
    claimed = math.prod(shape) * dtype.itemsize
    if claimed > data_bytes:
        raise FileLimitError(
            f"{name}: its header claims shape {shape} of {dtype} ({claimed:,} bytes) but the "
            f"file holds {max(data_bytes, 0):,} bytes of data"
        )


def _kind(mode: int) -> str:
    kinds = {
        stat.S_ISDIR: "a directory",
        stat.S_ISCHR: "a character device",
        stat.S_ISBLK: "a block device",
        stat.S_ISFIFO: "a FIFO",
        stat.S_ISSOCK: "a socket",
    }
    return next((kind for test, kind in kinds.items() if test(mode)), "not a plain file")


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__
