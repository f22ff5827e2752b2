"""The message-agnostic wire format: a msgpack map per message, numpy arrays inside it.

Every payload is a msgpack map {"schema": SCHEMA_VERSION, "type": <name>, <fields>...}. An
array travels as {"dtype": str, "shape": [int, ...], "zlib": bool, "data": bytes} in
little-endian byte order, zlib-compressed when larger than `compress_threshold_bytes` (and
only when that makes it smaller). Only the dtypes of `ARRAY_DTYPES` are accepted.

Decoding trusts nothing: the payload size is checked before unpacking, every field's type,
every array's dtype, rank and byte length, and the decompressed size is capped (a zlib bomb
stops at the size its shape declares). Any violation raises `ProtocolError` with a one-line
message. Never pickle.
"""

from __future__ import annotations

import math
import zlib
from typing import Any

import msgpack
import numpy as np

from mapex.grid import (  # noqa: F401  (re-exported: the wire quantisation)
    QUANTISATION_LEVELS,
    dequantise_probability,
    quantise_probability,
)
from services.config import ServicesConfig

SCHEMA_VERSION = 1
ARRAY_DTYPES = frozenset(
    {"uint8", "uint16", "int16", "int32", "int64", "float32", "float64", "bool"}
)
ARRAY_KEYS = frozenset({"dtype", "shape", "zlib", "data"})
ENVELOPE_KEYS = ("schema", "type")
DEFAULT_SERVICES = ServicesConfig()

Payload = bytes | bytearray | memoryview


class ProtocolError(ValueError):
    """A payload or key that breaks the wire protocol; the message is one line."""


def encode_array(array: np.ndarray, config: ServicesConfig = DEFAULT_SERVICES) -> dict[str, Any]:
    """A numpy array as its wire map (little-endian, compressed above the threshold)."""
    if array.dtype.name not in ARRAY_DTYPES:
        raise ProtocolError(f"dtype {array.dtype} is not sendable (allowed: {_allowed()})")
    little = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
    data = little.tobytes()
    compressed = False
    if len(data) > config.compress_threshold_bytes:
        packed = zlib.compress(data, config.zlib_level)
        if len(packed) < len(data):
            data, compressed = packed, True
    return {"dtype": array.dtype.name, "shape": list(array.shape), "zlib": compressed, "data": data}


def pack_message(
    type_name: str, fields: dict[str, Any], config: ServicesConfig = DEFAULT_SERVICES
) -> bytes:
    """The msgpack payload of message `type_name` with `fields` (arrays already encoded)."""
    clash = set(fields) & set(ENVELOPE_KEYS)
    if clash:
        raise ProtocolError(f"{type_name} message: field names {sorted(clash)} are reserved")
    payload = msgpack.packb(
        {"schema": SCHEMA_VERSION, "type": type_name, **fields}, use_bin_type=True
    )
    if len(payload) > config.max_message_bytes:
        raise ProtocolError(
            f"{type_name} message of {len(payload)} bytes exceeds the "
            f"{config.max_message_bytes}-byte limit"
        )
    return payload


def unpack_message(
    payload: Payload, config: ServicesConfig = DEFAULT_SERVICES, max_bytes: int | None = None
) -> FieldReader:
    """Check size, msgpack, envelope and schema version; return a reader over the fields.

    `max_bytes`: the receiver's own limit for what it expects (e.g. a world's step requests
    cannot hold more than its cells), on the payload and on its decoded arrays alike, below
    the global `max_message_bytes` and `max_decoded_bytes`. The msgpack objects are counted
    first (`max_message_objects`), so no payload becomes millions of Python objects."""
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise ProtocolError(f"payload must be bytes, got {type(payload).__name__}")
    size = memoryview(payload).nbytes
    limit = (
        config.max_message_bytes if max_bytes is None else min(max_bytes, config.max_message_bytes)
    )
    if size > limit:
        raise ProtocolError(f"payload of {size} bytes exceeds the {limit}-byte limit")
    count_objects(payload, config.max_message_objects)
    try:
        document = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except (ValueError, TypeError, msgpack.UnpackException) as error:
        raise ProtocolError(f"payload is not valid msgpack ({type(error).__name__})") from None
    if not isinstance(document, dict):
        raise ProtocolError(f"payload is a msgpack {type(document).__name__}, not a map")
    schema = document.pop("schema", None)
    if type(schema) is not int or schema != SCHEMA_VERSION:
        raise ProtocolError(f"schema version {schema!r} is not the supported {SCHEMA_VERSION}")
    type_name = document.pop("type", None)
    if not isinstance(type_name, str):
        raise ProtocolError(f"message type must be a string, got {type(type_name).__name__}")
    decoded = (
        config.max_decoded_bytes if max_bytes is None else min(max_bytes, config.max_decoded_bytes)
    )
    return FieldReader(type_name, document, config, decoded)


_FIXED = {  # msgpack type byte -> bytes that follow it (scalars of a fixed size)
    0xC0: 0, 0xC2: 0, 0xC3: 0, 0xCA: 4, 0xCB: 8, 0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8,
    0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8, 0xD4: 2, 0xD5: 3, 0xD6: 5, 0xD7: 9, 0xD8: 17,
}  # fmt: skip
_SIZED = {  # type byte -> (bytes of its length, extra bytes before the data, objects or bytes)
    0xC4: (1, 0, False), 0xC5: (2, 0, False), 0xC6: (4, 0, False),  # bin
    0xC7: (1, 1, False), 0xC8: (2, 1, False), 0xC9: (4, 1, False),  # ext
    0xD9: (1, 0, False), 0xDA: (2, 0, False), 0xDB: (4, 0, False),  # str
    0xDC: (2, 0, True), 0xDD: (4, 0, True),  # array: that many objects
    0xDE: (2, 0, True), 0xDF: (4, 0, True),  # map: twice that many
}  # fmt: skip


def count_objects(payload: Payload, limit: int) -> int:
    """The msgpack objects in `payload`, walked by their headers without building any;
    ProtocolError (one line) as soon as they exceed `limit`. Malformed data is left to the
    unpacker (the walk stops at the end of the bytes)."""
    data, at, pending, count = memoryview(payload).cast("B"), 0, 1, 0
    end = len(data)
    while pending and at < end:
        pending, count, byte = pending - 1, count + 1, data[at]
        if count > limit:
            raise ProtocolError(f"payload holds more than {limit} msgpack objects")
        at += 1
        if byte <= 0x7F or byte >= 0xE0:
            continue  # fixint
        if byte <= 0x8F:
            pending += 2 * (byte & 0x0F)  # fixmap
        elif byte <= 0x9F:
            pending += byte & 0x0F  # fixarray
        elif byte <= 0xBF:
            at += byte & 0x1F  # fixstr
        elif byte in _FIXED:
            at += _FIXED[byte]
        elif byte in _SIZED:
            width, extra, objects = _SIZED[byte]
            length = int.from_bytes(data[at : at + width], "big")
            at += width
            if objects:
                pending += length * (2 if byte >= 0xDE else 1)
            else:
                at += extra + length
        else:
            break  # 0xC1, never used: the unpacker says so
    return count


class FieldReader:
    """Typed, checked access to the fields of one unpacked message.

    Each accessor checks the wire type of one field and marks it read; `finish` rejects
    fields nobody read. Arrays are checked against their declared dtype, rank and byte
    length, and all of a message's arrays together may not exceed `max_decoded_bytes`.
    Decoded arrays are read-only views of the payload (copy to modify).
    """

    def __init__(
        self,
        type_name: str,
        fields: dict[str, Any],
        config: ServicesConfig,
        decoded_bytes: int | None = None,
    ) -> None:
        self.type_name = type_name
        self._fields = fields
        self._unread = set(fields)
        self._budget_bytes = config.max_decoded_bytes if decoded_bytes is None else decoded_bytes

    def error(self, what: str) -> ProtocolError:
        """A ProtocolError naming this message's type."""
        return ProtocolError(f"{self.type_name} message: {what}")

    def integer(self, name: str) -> int:
        """An int field (bool is not an int here)."""
        return self._typed(name, int, "an integer")

    def text(self, name: str) -> str:
        """A str field."""
        return self._typed(name, str, "a string")

    def flag(self, name: str) -> bool:
        """A bool field."""
        return self._typed(name, bool, "a boolean")

    def number(self, name: str) -> float:
        """A float field (ints accepted)."""
        value = self._take(name)
        if type(value) not in (int, float):
            raise self.error(f"field '{name}' must be a number, got {type(value).__name__}")
        return float(value)

    def optional_number(self, name: str) -> float | None:
        """A float field that may be nil."""
        return None if self._is_nil(name) else self.number(name)

    def added_number(self, name: str) -> float | None:
        """A float field added to v1 later: None when nil or absent (older senders)."""
        return self.optional_number(name) if name in self._fields else None

    def added_text(self, name: str) -> str | None:
        """A str field added to v1 later: None when nil or absent (older senders)."""
        if name not in self._fields or self._is_nil(name):
            return None
        return self.text(name)

    def added_cell(self, name: str) -> tuple[int, int] | None:
        """A (row, col) field added to v1 later: None when nil or absent (older senders)."""
        return self.optional_cell(name) if name in self._fields else None

    def cell(self, name: str) -> tuple[int, int]:
        """A (row, col) field sent as a two-integer list."""
        value = self._take(name)
        if not (isinstance(value, list) and len(value) == 2 and all(type(v) is int for v in value)):
            raise self.error(f"field '{name}' must be a [row, col] pair of integers")
        return value[0], value[1]

    def optional_cell(self, name: str) -> tuple[int, int] | None:
        """A (row, col) field that may be nil."""
        return None if self._is_nil(name) else self.cell(name)

    def array(self, name: str, dtype: str, ndim: int) -> np.ndarray:
        """An array field of exactly `dtype` and rank `ndim`."""
        wire = self._take(name)
        if not isinstance(wire, dict) or set(wire) != ARRAY_KEYS:
            raise self.error(f"field '{name}' must be an array map with keys {sorted(ARRAY_KEYS)}")
        if wire["dtype"] != dtype:
            raise self.error(f"array '{name}' must be {dtype}, got {wire['dtype']!r}")
        shape = wire["shape"]
        if not (
            isinstance(shape, list)
            and len(shape) == ndim
            and all(type(n) is int and n >= 0 for n in shape)
        ):
            raise self.error(f"array '{name}' must have a shape of {ndim} non-negative integers")
        if type(wire["zlib"]) is not bool or not isinstance(wire["data"], bytes):
            raise self.error(f"array '{name}' needs a boolean 'zlib' and bytes 'data'")
        return self._array_from_bytes(name, np.dtype(dtype), shape, wire["zlib"], wire["data"])

    def finish(self) -> None:
        """Reject fields that no accessor read."""
        if self._unread:
            raise self.error(f"unexpected fields {sorted(map(str, self._unread))}")

    def _take(self, name: str) -> Any:
        if name not in self._fields:
            raise self.error(f"missing field '{name}'")
        self._unread.discard(name)
        return self._fields[name]

    def is_nil(self, name: str) -> bool:
        """Whether field `name` is present and nil (then it counts as read)."""
        return self._is_nil(name)

    def _is_nil(self, name: str) -> bool:
        """Whether field `name` is present and nil (then it counts as read)."""
        if name in self._fields and self._fields[name] is None:
            self._unread.discard(name)
            return True
        return False

    def _typed(self, name: str, kind: type, description: str) -> Any:
        value = self._take(name)
        if type(value) is not kind:
            raise self.error(f"field '{name}' must be {description}, got {type(value).__name__}")
        return value

    def _array_from_bytes(
        self, name: str, dtype: np.dtype, shape: list[int], compressed: bool, data: bytes
    ) -> np.ndarray:
        expected = math.prod(shape) * dtype.itemsize
        if expected > self._budget_bytes:
            raise self.error(
                f"array '{name}' declares {expected} bytes, over the decoded-size limit"
            )
        self._budget_bytes -= expected
        raw = self._inflate(name, data, expected) if compressed else data
        if len(raw) != expected:
            raise self.error(
                f"array '{name}' holds {len(raw)} bytes, its dtype and shape need {expected}"
            )
        if dtype == np.bool_ and expected and np.frombuffer(raw, np.uint8).max() > 1:
            raise self.error(f"bool array '{name}' holds bytes other than 0 and 1")
        little = np.frombuffer(raw, dtype=dtype.newbyteorder("<")).reshape(shape)
        return little.astype(dtype, copy=False)

    def _inflate(self, name: str, data: bytes, expected: int) -> bytes:
        """Decompress at most expected + 1 bytes, so an oversized stream is caught cheaply."""
        inflater = zlib.decompressobj()
        try:
            raw = inflater.decompress(data, expected + 1)
        except zlib.error:
            raise self.error(f"array '{name}' is not a valid zlib stream") from None
        if len(raw) > expected:
            raise self.error(f"array '{name}' decompresses to more than the {expected} bytes")
        if not inflater.eof or inflater.unused_data:
            raise self.error(f"array '{name}' zlib stream is truncated or has trailing bytes")
        return raw


def _allowed() -> str:
    return ", ".join(sorted(ARRAY_DTYPES))
