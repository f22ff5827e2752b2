"""Version-1 messages: what travels on the keys of `services.keys`.

Messages are frozen dataclasses with `encode()` and `decode()` over the generic format of
`services.codec`; constructing or decoding one that breaks its rules raises
`ProtocolError` with a one-line message.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import math
import operator
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, TypeVar

import numpy as np

from mapex.grid import OCCUPIED, Cell, observed_to_probability
from mapex.sensor import Scan
from mapex.worlds.base import World
from services.codec import (
    DEFAULT_SERVICES,
    FieldReader,
    Payload,
    ProtocolError,
    dequantise_probability,
    encode_array,
    pack_message,
    quantise_probability,
    unpack_message,
)
from services.config import ServicesConfig
from services.keys import MEMBERS, is_valid_id

MapKind = Literal["observed", "main", "mean", "variance"]
MAP_KINDS = ("observed", "main", "mean", "variance")
STATUS_STATES = ("starting", "running", "finished", "failed")
_INT32_MAX = np.iinfo(np.int32).max

M = TypeVar("M", bound="Message")


class Message:
    """Base of every payload: `encode()` to msgpack bytes, `decode()` back, fully checked.

    A subclass names its wire `TYPE`, lists its fields in `_fields` and reads them back in
    `_read`; value rules live in `__post_init__`, so they hold for both directions.
    """

    TYPE: ClassVar[str]
    _REGISTRY: ClassVar[dict[str, type[Message]]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        Message._REGISTRY[cls.TYPE] = cls

    def encode(self, config: ServicesConfig = DEFAULT_SERVICES) -> bytes:
        """The msgpack payload of this message."""
        return pack_message(self.TYPE, self._fields(config), config)

    @classmethod
    def decode(
        cls: type[M],
        payload: Payload,
        config: ServicesConfig = DEFAULT_SERVICES,
        max_bytes: int | None = None,
    ) -> M:
        """Parse and check a payload that must hold a message of this type (`max_bytes`:
        the receiver's limit, `unpack_message`)."""
        reader = unpack_message(payload, config, max_bytes)
        if reader.type_name != cls.TYPE:
            raise ProtocolError(f"expected a {cls.TYPE} message, got type {reader.type_name!r}")
        return cls._read_all(reader)

    @classmethod
    def _read_all(cls: type[M], reader: FieldReader) -> M:
        message = cls._read(reader)
        reader.finish()
        return message

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def _read(cls: type[M], reader: FieldReader) -> M:
        raise NotImplementedError


def decode_message(
    payload: Payload,
    expected: tuple[type[Message], ...] | None = None,
    config: ServicesConfig = DEFAULT_SERVICES,
    max_bytes: int | None = None,
) -> Message:
    """Decode a payload of any message type (or of one of `expected`), fully checked
    (`max_bytes`: the receiver's limit, `unpack_message`)."""
    reader = unpack_message(payload, config, max_bytes)
    cls = Message._REGISTRY.get(reader.type_name)
    if cls is None:
        raise ProtocolError(f"unknown message type {reader.type_name!r}")
    if expected is not None and cls not in expected:
        names = ", ".join(c.TYPE for c in expected)
        raise ProtocolError(f"expected a message of type {names}, got {cls.TYPE!r}")
    return cls._read_all(reader)


@dataclass(frozen=True, eq=False)
class ScanReply(Message):
    """One robot's scan after a step, published on `scan`: a `mapex.sensor.Scan`.

    pose (row, col); n_cells uint16 (n_rays,); hit bool (n_rays,); t the step it was taken
    after (as the pose's), None when not said (older worlds, and inside the world).
    """

    TYPE: ClassVar[str] = "scan_reply"
    pose: Cell
    n_cells: np.ndarray
    hit: np.ndarray
    t: int | None = None

    def __post_init__(self) -> None:
        _set(self, "pose", _checked_cell(self.TYPE, "pose", self.pose))
        _check_array(self.TYPE, "n_cells", self.n_cells, np.uint16, 1)
        _check_array(self.TYPE, "hit", self.hit, np.bool_, 1)
        if self.n_cells.shape != self.hit.shape:
            raise ProtocolError(f"{self.TYPE}: n_cells and hit must have one length")
        if self.t is not None:
            _set(self, "t", _checked_step(self.TYPE, self.t))

    @classmethod
    def from_scan(cls, scan: Scan, t: int | None = None) -> ScanReply:
        """The reply carrying `scan` (taken after step `t`)."""
        return cls(scan.pose, scan.n_cells, scan.hit, t)

    def to_scan(self) -> Scan:
        """The `mapex.sensor.Scan` this reply carries (arrays copied, then made read-only)."""
        return Scan(self.pose, self.n_cells.copy(), self.hit.copy())

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        fields = {
            "pose": list(self.pose),
            "n_cells": encode_array(self.n_cells, config),
            "hit": encode_array(self.hit, config),
        }
        return fields if self.t is None else {**fields, "t": self.t}

    @classmethod
    def _read(cls, reader: FieldReader) -> ScanReply:
        pose = reader.cell("pose")
        n_cells, hit = reader.array("n_cells", "uint16", 1), reader.array("hit", "bool", 1)
        return cls(pose, n_cells, hit, _whole(reader.added_number("t")))


MESSAGE_OVERHEAD_BYTES = 64 * 2**10  # a message's envelope, scalars and array headers, at most


def map_message_bytes(cells: int, maps: int = 1, extra_bytes: int = 0) -> int:
    """The most a message holding `maps` maps of `cells` one-byte cells (and `extra_bytes`
    of other arrays) can take, encoded or decoded: a receiver's `max_bytes`, so that no
    message can be larger than what the run it belongs to can hold."""
    return maps * cells + extra_bytes + MESSAGE_OVERHEAD_BYTES


STEP_KEY_CONTEXT = b"mapex step key v1|"  # step_key: HMAC(run token, this + run id)
STEP_MAC_CONTEXT = b"mapex step request v1"  # the first bytes a step request's MAC covers
_MAC_HEX = re.compile(r"[0-9a-f]{64}")  # an HMAC-SHA256, lowercase hex


def step_key(run_token: str, run: str) -> bytes:
    """The key a run's planners sign their step requests with and its world checks them
    with: HMAC-SHA256 of `STEP_KEY_CONTEXT` + the run id under the run token. It proves the
    token without revealing it, and a MAC made with it is worth nothing in another run."""
    return hmac.new(run_token.encode(), STEP_KEY_CONTEXT + run.encode(), hashlib.sha256).digest()


WORLD_REPLY_CONTEXT = b"mapex world reply v1"  # the first bytes a world reply's MAC covers


def world_reply_mac(key: bytes, key_expr: str, query: bytes, reply: bytes) -> bytes:
    """The MAC (HMAC-SHA256, 32 bytes) a run's world attaches to each reply it sends on
    `key_expr` (step, world_info, ground_truth) under the run's step key: it covers the
    query's payload too, so a planner takes only its own world's answer to what it asked,
    and a reply cannot be moved to another key, run or query (docs/design.md#trust)."""
    digest = hmac.new(key, digestmod=hashlib.sha256)
    for part in (WORLD_REPLY_CONTEXT, key_expr.encode(), query, reply):
        digest.update(_framed(part))
    return digest.digest()


def world_reply_signed(key: bytes, key_expr: str, query: bytes, reply: bytes, mac: bytes) -> bool:
    """Whether `mac` is the world's MAC of `reply` to `query` on `key_expr` under `key`
    (compared in constant time)."""
    return hmac.compare_digest(mac, world_reply_mac(key, key_expr, query, reply))


@dataclass(frozen=True, eq=False)
class StepRequest(Message):
    """A robot's planner -> its world on `step` (docs/protocol.md): its motion of step
    seq - 1, whether it has nothing left to explore, and its new claim when it re-planned
    with a method that coordinates.

    `mac`: in a run with a run token, HMAC-SHA256 (hex) under `step_key(token, run)` of
    everything the request asks (`signed_bytes`): run id, robot index, seq, cells, done,
    claimed and the claim, so the token never travels and a MAC cannot be moved to
    another run, robot, step or motion (docs/design.md#trust).
    """

    TYPE: ClassVar[str] = "step_request"
    seq: int
    cells: np.ndarray
    done: bool
    claimed: bool
    claim_goal: Cell | None
    claim_score: float | None
    claim_visible: np.ndarray | None
    mac: str | None = None

    def __post_init__(self) -> None:
        _set(self, "seq", _checked_count(self.TYPE, "seq", self.seq))
        _set(self, "cells", _checked_cells(self.TYPE, "cells", self.cells))
        if self.claim_goal is not None:
            _set(self, "claim_goal", _checked_cell(self.TYPE, "claim_goal", self.claim_goal))
            _check_array(self.TYPE, "claim_visible", self.claim_visible, np.bool_, 2)
            if self.claim_score is None or not -math.inf <= self.claim_score < math.inf:
                raise ProtocolError(f"{self.TYPE}: a claim needs a claim_score below +inf")
        if self.mac is not None and not (
            isinstance(self.mac, str) and _MAC_HEX.fullmatch(self.mac)
        ):
            raise ProtocolError(f"{self.TYPE}: mac must be 64 lowercase hex digits")

    def signed(self, key: bytes, run: str, robot: int) -> StepRequest:
        """This request carrying its MAC under `key` as robot `robot` of `run`."""
        return dataclasses.replace(self, mac=self.mac_under(key, run, robot))

    def signed_by(self, key: bytes, run: str, robot: int) -> bool:
        """Whether this request carries the MAC of robot `robot` of `run` under `key`
        (compared in constant time)."""
        expected = self.mac_under(key, run, robot)
        return self.mac is not None and hmac.compare_digest(self.mac, expected)

    def mac_under(self, key: bytes, run: str, robot: int) -> str:
        """HMAC-SHA256 (hex) under `key` of `signed_bytes(run, robot)`."""
        digest = hmac.new(key, digestmod=hashlib.sha256)
        for part in self.signed_bytes(run, robot):
            digest.update(part)
        return digest.hexdigest()

    def signed_bytes(self, run: str, robot: int) -> Iterator[bytes]:
        """The canonical encoding a MAC covers, in parts: every variable-length part is
        length-prefixed, so no two requests share it. Fields that do not travel (a claim's
        score and cells without a goal) are not in it."""
        yield _framed(STEP_MAC_CONTEXT)
        yield _framed(run.encode())
        yield struct.pack("<QQ??", robot, self.seq, self.done, self.claimed)
        yield _framed(np.ascontiguousarray(self.cells, dtype="<i4").tobytes())
        if self.claim_goal is None:
            yield b"\x00"
            return
        visible = np.ascontiguousarray(self.claim_visible, dtype=np.bool_)
        yield struct.pack("<?QQd", True, *self.claim_goal, float(self.claim_score))
        yield struct.pack("<QQ", *visible.shape)
        yield _framed(visible.tobytes())

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        has_claim = self.claim_goal is not None
        return {
            "seq": self.seq, "cells": encode_array(self.cells, config), "done": self.done,
            "claimed": self.claimed,
            "claim_goal": list(self.claim_goal) if has_claim else None,
            "claim_score": float(self.claim_score) if has_claim else None,
            "claim_visible": encode_array(self.claim_visible, config) if has_claim else None,
            "mac": self.mac,
        }  # fmt: skip

    @classmethod
    def _read(cls, reader: FieldReader) -> StepRequest:
        seq, cells = reader.integer("seq"), reader.array("cells", "int32", 2)
        done, claimed = reader.flag("done"), reader.flag("claimed")
        goal, score = reader.optional_cell("claim_goal"), reader.optional_number("claim_score")
        visible = (
            None if reader.is_nil("claim_visible") else reader.array("claim_visible", "bool", 2)
        )
        return cls(seq, cells, done, claimed, goal, score, visible, reader.added_text("mac"))


def _framed(data: bytes) -> bytes:
    """`data` behind its length (8 bytes, little-endian)."""
    return struct.pack("<Q", len(data)) + data


@dataclass(frozen=True, eq=False)
class StepReply(Message):
    """The world -> every robot's planner, the reply to the `step_request`s of one seq
    (docs/protocol.md): every robot's scan after that step, the claims made at it, the
    robots that stood still or are lost, and whether the team is finished."""

    TYPE: ClassVar[str] = "step_reply"
    seq: int
    finished: bool
    poses: np.ndarray
    n_cells: np.ndarray
    hit: np.ndarray
    stood_still: np.ndarray
    claim_state: np.ndarray
    claim_goals: np.ndarray
    claim_scores: np.ndarray
    claim_visible: np.ndarray
    lost: np.ndarray

    def __post_init__(self) -> None:
        _set(self, "seq", _checked_count(self.TYPE, "seq", self.seq))
        for name, dtype, ndim in STEP_REPLY_ARRAYS:
            _check_array(self.TYPE, name, getattr(self, name), dtype, ndim)
        robots = len(self.claim_state)
        scanned = {len(self.poses), len(self.n_cells), len(self.hit)}
        claims = {len(getattr(self, name)) for name in CLAIM_FIELDS}
        flags = {len(self.stood_still), len(self.lost)}
        if claims != {robots} or scanned not in ({robots}, {0}) or flags != {robots}:
            raise ProtocolError(f"{self.TYPE}: every per-robot array needs {robots} rows")
        if self.claim_state.max(initial=0) > 2:
            raise ProtocolError(f"{self.TYPE}: claim_state holds codes other than 0, 1, 2")
        made = int(np.count_nonzero(self.claim_state == CLAIM_MADE))
        if len(self.claim_visible) != made:
            raise ProtocolError(
                f"{self.TYPE}: claim_visible needs one row per new claim ({made}), "
                f"got {len(self.claim_visible)}"
            )

    def visible_of(self, robot: int) -> np.ndarray:
        """The claimed cells of `robot`'s new claim (claim_state 1)."""
        return self.claim_visible[int(np.count_nonzero(self.claim_state[:robot] == CLAIM_MADE))]

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        fields = {
            name: encode_array(getattr(self, name), config) for name, _, _ in STEP_REPLY_ARRAYS
        }
        return {"seq": self.seq, "finished": self.finished, **fields}

    @classmethod
    def _read(cls, reader: FieldReader) -> StepReply:
        seq, finished = reader.integer("seq"), reader.flag("finished")
        arrays = {
            name: reader.array(name, np.dtype(dtype).name, ndim)
            for name, dtype, ndim in STEP_REPLY_ARRAYS
        }
        return cls(seq, finished, **arrays)


CLAIM_NONE, CLAIM_MADE, CLAIM_WITHDRAWN = 0, 1, 2  # claim_state codes of a step reply
CLAIM_FIELDS = ("claim_state", "claim_goals", "claim_scores")  # a row per robot
STEP_REPLY_ARRAYS = (
    ("poses", np.int32, 2),
    ("n_cells", np.uint16, 2),
    ("hit", np.bool_, 2),
    ("stood_still", np.bool_, 1),
    ("claim_state", np.uint8, 1),
    ("claim_goals", np.int32, 2),
    ("claim_scores", np.float64, 1),
    ("claim_visible", np.bool_, 3),
    ("lost", np.bool_, 1),
)


@dataclass(frozen=True)
class PoseMessage(Message):
    """World -> anyone on `pose`: the robot's cell after step `t`."""

    TYPE: ClassVar[str] = "pose"
    t: int
    pose: Cell

    def __post_init__(self) -> None:
        _set(self, "t", _checked_step(self.TYPE, self.t))
        _set(self, "pose", _checked_cell(self.TYPE, "pose", self.pose))

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {"t": self.t, "pose": list(self.pose)}

    @classmethod
    def _read(cls, reader: FieldReader) -> PoseMessage:
        return cls(reader.integer("t"), reader.cell("pose"))


@dataclass(frozen=True, eq=False)
class PredictRequest(Message):
    """Planner -> one predictor worker: predict the unknown cells of an observed-map crop.

    observed: uint8 (h, w) codes of `mapex.grid` (FREE, UNKNOWN, OCCUPIED).
    budget_s: how long the planner waits for the reply; a worker drops a request that
    waited longer than this in its queue (the planner has given up on it). None: no limit.
    Added to v1 later, each sent only when set (so workers older than them still read the
    requests of the default predictor): `run` and `origin`, the run whose map the crop is
    cut from and the crop's top-left cell (row, col) in it, which the oracle worker needs
    (it answers with that run's ground truth), given together; `predictor`, the predictor
    the planner runs (None: the default, `lama`), which a worker serving another refuses.
    """

    TYPE: ClassVar[str] = "predict_request"
    request_id: int
    observed: np.ndarray
    budget_s: float | None = None
    run: str | None = None
    origin: Cell | None = None
    predictor: str | None = None

    def __post_init__(self) -> None:
        _set(self, "request_id", _checked_count(self.TYPE, "request_id", self.request_id))
        _check_map(self.TYPE, "observed", self.observed, np.uint8)
        _check_codes(self.TYPE, "observed", self.observed)
        if self.budget_s is not None:
            _set(self, "budget_s", _checked_number(self.TYPE, "budget_s", self.budget_s))
        if (self.run is None) != (self.origin is None):
            raise ProtocolError(f"{self.TYPE}: run and origin go together")
        if self.run is not None and not is_valid_id(self.run):
            raise ProtocolError(f"{self.TYPE}: run {self.run!r} is not a valid run id")
        if self.origin is not None:
            _set(self, "origin", _checked_cell(self.TYPE, "origin", self.origin))
        if self.predictor is not None and not is_valid_id(self.predictor):
            raise ProtocolError(f"{self.TYPE}: predictor {self.predictor!r} is not a valid name")

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        observed = encode_array(self.observed, config)
        fields = {"request_id": self.request_id, "observed": observed, "budget_s": self.budget_s}
        if self.run is not None:
            fields |= {"run": self.run, "origin": list(self.origin)}
        return fields if self.predictor is None else {**fields, "predictor": self.predictor}

    @classmethod
    def _read(cls, reader: FieldReader) -> PredictRequest:
        request_id, observed = reader.integer("request_id"), reader.array("observed", "uint8", 2)
        return cls(
            request_id, observed, reader.added_number("budget_s"), reader.added_text("run"),
            reader.added_cell("origin"), reader.added_text("predictor"),
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class PredictReply(Message):
    """Predictor worker -> planner: one member's occupancy probabilities for the crop.

    probabilities_u8: uint8 (h, w), quantised with `quantise_probability` (p = q / 255).
    compute_ms: the worker's compute time for this query, in milliseconds.
    """

    TYPE: ClassVar[str] = "predict_reply"
    request_id: int
    member: str
    probabilities_u8: np.ndarray
    worker_id: str
    compute_ms: float

    def __post_init__(self) -> None:
        _set(self, "request_id", _checked_count(self.TYPE, "request_id", self.request_id))
        if self.member not in MEMBERS:
            raise ProtocolError(f"{self.TYPE}: member {self.member!r} is not one of {MEMBERS}")
        _check_map(self.TYPE, "probabilities_u8", self.probabilities_u8, np.uint8)
        if not is_valid_id(self.worker_id):
            raise ProtocolError(f"{self.TYPE}: worker_id {self.worker_id!r} is not a valid id")
        _set(self, "compute_ms", _checked_number(self.TYPE, "compute_ms", self.compute_ms))

    @classmethod
    def from_probabilities(
        cls,
        request_id: int,
        member: str,
        probabilities: np.ndarray,
        worker_id: str,
        compute_ms: float,
    ) -> PredictReply:
        """The reply for float `probabilities` in [0, 1] (quantised here)."""
        return cls(request_id, member, quantise_probability(probabilities), worker_id, compute_ms)

    def probabilities(self) -> np.ndarray:
        """The probabilities as float32 (h, w), within 1/510 of what was sent."""
        return dequantise_probability(self.probabilities_u8)

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {
            "request_id": self.request_id,
            "member": self.member,
            "probabilities_u8": encode_array(self.probabilities_u8, config),
            "worker_id": self.worker_id,
            "compute_ms": self.compute_ms,
        }

    @classmethod
    def _read(cls, reader: FieldReader) -> PredictReply:
        return cls(
            reader.integer("request_id"),
            reader.text("member"),
            reader.array("probabilities_u8", "uint8", 2),
            reader.text("worker_id"),
            reader.number("compute_ms"),
        )


@dataclass(frozen=True, eq=False)
class MapMessage(Message):
    """Planner -> anyone on `observed_map` and `prediction/*`: a whole map after step `t`.

    map_u8: uint8 (rows, cols); for kind "observed" the codes of `mapex.grid`, otherwise
    probabilities quantised with `quantise_probability` (the variance on the same 0..1 scale).
    """

    TYPE: ClassVar[str] = "map"
    t: int
    kind: MapKind
    map_u8: np.ndarray

    def __post_init__(self) -> None:
        _set(self, "t", _checked_step(self.TYPE, self.t))
        if self.kind not in MAP_KINDS:
            raise ProtocolError(f"{self.TYPE}: kind {self.kind!r} is not one of {MAP_KINDS}")
        _check_map(self.TYPE, "map_u8", self.map_u8, np.uint8)
        if self.kind == "observed":
            _check_codes(self.TYPE, "map_u8", self.map_u8)

    @classmethod
    def from_probabilities(cls, t: int, kind: MapKind, probabilities: np.ndarray) -> MapMessage:
        """A prediction map (kind main, mean or variance) from float values in [0, 1]."""
        if kind == "observed":
            raise ValueError("an observed map travels as its uint8 codes, not probabilities")
        return cls(t, kind, quantise_probability(probabilities))

    def probabilities(self) -> np.ndarray:
        """float32 occupancy values: code / 2 for observed maps, q / 255 otherwise."""
        if self.kind == "observed":
            return observed_to_probability(self.map_u8)
        return dequantise_probability(self.map_u8)

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {"t": self.t, "kind": self.kind, "map_u8": encode_array(self.map_u8, config)}

    @classmethod
    def _read(cls, reader: FieldReader) -> MapMessage:
        return cls(reader.integer("t"), reader.text("kind"), reader.array("map_u8", "uint8", 2))


@dataclass(frozen=True, eq=False)
class FrontiersMessage(Message):
    """Planner -> anyone on `frontiers`: frontier points int32 (K, 2), scores float64 (K,)."""

    TYPE: ClassVar[str] = "frontiers"
    t: int
    cells: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        _set(self, "t", _checked_step(self.TYPE, self.t))
        _set(self, "cells", _checked_cells(self.TYPE, "cells", self.cells))
        _check_array(self.TYPE, "scores", self.scores, np.float64, 1)
        if len(self.scores) != len(self.cells):
            raise ProtocolError(f"{self.TYPE}: one score per frontier cell is needed")

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {
            "t": self.t,
            "cells": encode_array(self.cells, config),
            "scores": encode_array(self.scores, config),
        }

    @classmethod
    def _read(cls, reader: FieldReader) -> FrontiersMessage:
        t, cells = reader.integer("t"), reader.array("cells", "int32", 2)
        return cls(t, cells, reader.array("scores", "float64", 1))


@dataclass(frozen=True)
class GoalMessage(Message):
    """Planner -> anyone on `goal`: the current goal cell, or None when there is none."""

    TYPE: ClassVar[str] = "goal"
    t: int
    goal: Cell | None

    def __post_init__(self) -> None:
        _set(self, "t", _checked_step(self.TYPE, self.t))
        if self.goal is not None:
            _set(self, "goal", _checked_cell(self.TYPE, "goal", self.goal))

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {"t": self.t, "goal": None if self.goal is None else list(self.goal)}

    @classmethod
    def _read(cls, reader: FieldReader) -> GoalMessage:
        return cls(reader.integer("t"), reader.optional_cell("goal"))


@dataclass(frozen=True, eq=False)
class PathMessage(Message):
    """Planner -> anyone on `path`: the planned path int32 (k, 2) from the robot to the goal."""

    TYPE: ClassVar[str] = "path"
    t: int
    cells: np.ndarray

    def __post_init__(self) -> None:
        _set(self, "t", _checked_step(self.TYPE, self.t))
        _set(self, "cells", _checked_cells(self.TYPE, "cells", self.cells))

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {"t": self.t, "cells": encode_array(self.cells, config)}

    @classmethod
    def _read(cls, reader: FieldReader) -> PathMessage:
        return cls(reader.integer("t"), reader.array("cells", "int32", 2))


@dataclass(frozen=True)
class MetricsMessage(Message):
    """Planner -> anyone on `metrics`: docs/algorithms.md#metrics values at step `t`, all in [0, 1].

    tu is None at steps where TU is not computed; degraded is True when this step's
    prediction lacked members (docs/design.md#reliability).
    """

    TYPE: ClassVar[str] = "metrics"
    t: int
    coverage: float
    iou: float
    tu: float | None
    degraded: bool

    def __post_init__(self) -> None:
        _set(self, "t", _checked_step(self.TYPE, self.t))
        _set(self, "coverage", _checked_number(self.TYPE, "coverage", self.coverage, 1.0))
        _set(self, "iou", _checked_number(self.TYPE, "iou", self.iou, 1.0))
        if self.tu is not None:
            _set(self, "tu", _checked_number(self.TYPE, "tu", self.tu, 1.0))
        if not isinstance(self.degraded, bool | np.bool_):
            raise ProtocolError(f"{self.TYPE}: degraded must be a bool")
        _set(self, "degraded", bool(self.degraded))

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {
            "t": self.t,
            "coverage": self.coverage,
            "iou": self.iou,
            "tu": self.tu,
            "degraded": self.degraded,
        }

    @classmethod
    def _read(cls, reader: FieldReader) -> MetricsMessage:
        return cls(
            reader.integer("t"),
            reader.number("coverage"),
            reader.number("iou"),
            reader.optional_number("tu"),
            reader.flag("degraded"),
        )


@dataclass(frozen=True)
class StatusMessage(Message):
    """Planner -> anyone on `status`: the run's state (one of STATUS_STATES) and a detail line."""

    TYPE: ClassVar[str] = "status"
    t: int
    state: str
    detail: str = ""

    def __post_init__(self) -> None:
        _set(self, "t", _checked_step(self.TYPE, self.t))
        if self.state not in STATUS_STATES:
            raise ProtocolError(f"{self.TYPE}: state {self.state!r} is not one of {STATUS_STATES}")
        _set(self, "detail", _one_line(self.TYPE, "detail", self.detail))

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {"t": self.t, "state": self.state, "detail": self.detail}

    @classmethod
    def _read(cls, reader: FieldReader) -> StatusMessage:
        return cls(reader.integer("t"), reader.text("state"), reader.text("detail"))


@dataclass(frozen=True, eq=False)
class WorldInfo(Message):
    """World -> anyone on `world_info`: map size (rows, cols), cell size, name, start cells,
    and the sensor and motion settings the world simulates (None: not said)."""

    TYPE: ClassVar[str] = "world_info"
    name: str
    shape: tuple[int, int]
    resolution_m: float
    starts: np.ndarray
    n_rays: int | None = None
    range_cells: int | None = None
    cells_per_step: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ProtocolError(f"{self.TYPE}: name must be a non-empty string")
        shape = _checked_cell(self.TYPE, "shape", self.shape)
        if min(shape) < 1:
            raise ProtocolError(f"{self.TYPE}: shape {shape} must be positive")
        _set(self, "shape", shape)
        resolution = _checked_number(self.TYPE, "resolution_m", self.resolution_m)
        if resolution <= 0:
            raise ProtocolError(f"{self.TYPE}: resolution_m must be positive")
        _set(self, "resolution_m", resolution)
        starts = _checked_cells(self.TYPE, "starts", self.starts)
        if len(starts) and (starts >= np.array(shape)).any():
            raise ProtocolError(f"{self.TYPE}: a start cell lies outside the {shape} map")
        _set(self, "starts", starts)
        for name in WORLD_SETTINGS:
            if getattr(self, name) is not None:
                _set(self, name, _checked_count(self.TYPE, name, getattr(self, name)))

    def settings(self) -> dict[str, int | None]:
        """The sensor and motion settings the world simulates, by field name."""
        return {name: getattr(self, name) for name in WORLD_SETTINGS}

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {
            "name": self.name,
            "shape": list(self.shape),
            "resolution_m": self.resolution_m,
            "starts": encode_array(self.starts, config),
            **{name: value for name, value in self.settings().items() if value is not None},
        }

    @classmethod
    def _read(cls, reader: FieldReader) -> WorldInfo:
        name, shape = reader.text("name"), reader.cell("shape")
        resolution, starts = reader.number("resolution_m"), reader.array("starts", "int32", 2)
        settings = [reader.added_number(field) for field in WORLD_SETTINGS]
        return cls(name, shape, resolution, starts, *(_whole(value) for value in settings))


WORLD_SETTINGS = ("n_rays", "range_cells", "cells_per_step")  # world_info's shared settings


def _whole(value: float | None) -> int | float | None:
    """A count read as a number: an int when whole (else left for __post_init__ to refuse)."""
    return int(value) if value is not None and float(value).is_integer() else value


@dataclass(frozen=True, eq=False)
class GroundTruth(Message):
    """World -> anyone on `ground_truth`: walls and valid space, bool (rows, cols) each."""

    TYPE: ClassVar[str] = "ground_truth"
    occupancy: np.ndarray
    valid_space: np.ndarray

    def __post_init__(self) -> None:
        _check_map(self.TYPE, "occupancy", self.occupancy, np.bool_)
        _check_map(self.TYPE, "valid_space", self.valid_space, np.bool_)
        if self.occupancy.shape != self.valid_space.shape:
            raise ProtocolError(f"{self.TYPE}: occupancy and valid_space differ in shape")

    @classmethod
    def from_world(cls, world: World) -> GroundTruth:
        """The ground truth of `world`."""
        return cls(world.occupancy, world.valid_space)

    def to_world(self, name: str, resolution_m: float) -> World:
        """A `World` named `name` (from WorldInfo) over copies of these maps."""
        return World(name, self.occupancy.copy(), self.valid_space.copy(), resolution_m)

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {
            "occupancy": encode_array(self.occupancy, config),
            "valid_space": encode_array(self.valid_space, config),
        }

    @classmethod
    def _read(cls, reader: FieldReader) -> GroundTruth:
        return cls(reader.array("occupancy", "bool", 2), reader.array("valid_space", "bool", 2))


@dataclass(frozen=True)
class HealthReply(Message):
    """Predictor worker -> prober, on `health`: answered at once, even mid-prediction.

    busy_s: how long the prediction being computed has been running (0 when idle), so a
    worker stuck in one (a deadlock, a stuck GPU) shows as busy for ever; queued: requests
    waiting behind it; answered and dropped (past their budget) since the worker started.
    """

    TYPE: ClassVar[str] = "health"
    member: str
    worker_id: str
    busy_s: float
    queued: int
    answered: int
    dropped: int

    def __post_init__(self) -> None:
        if self.member not in MEMBERS:
            raise ProtocolError(f"{self.TYPE}: member {self.member!r} is not one of {MEMBERS}")
        if not is_valid_id(self.worker_id):
            raise ProtocolError(f"{self.TYPE}: worker_id {self.worker_id!r} is not a valid id")
        _set(self, "busy_s", _checked_number(self.TYPE, "busy_s", self.busy_s))
        for name in ("queued", "answered", "dropped"):
            _set(self, name, _checked_count(self.TYPE, name, getattr(self, name)))

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {
            "member": self.member, "worker_id": self.worker_id, "busy_s": self.busy_s,
            "queued": self.queued, "answered": self.answered, "dropped": self.dropped,
        }  # fmt: skip

    @classmethod
    def _read(cls, reader: FieldReader) -> HealthReply:
        member, worker_id, busy_s = (
            reader.text("member"),
            reader.text("worker_id"),
            reader.number("busy_s"),
        )
        counts = (reader.integer(name) for name in ("queued", "answered", "dropped"))
        return cls(member, worker_id, busy_s, *counts)


@dataclass(frozen=True)
class ErrorReply(Message):
    """Any queryable -> querier: why a query was refused (made one line)."""

    TYPE: ClassVar[str] = "error"
    message: str

    def __post_init__(self) -> None:
        _set(self, "message", _one_line(self.TYPE, "message", self.message))

    def _fields(self, config: ServicesConfig) -> dict[str, Any]:
        return {"message": self.message}

    @classmethod
    def _read(cls, reader: FieldReader) -> ErrorReply:
        return cls(reader.text("message"))


# ------------------------------------------------------------------------- value rule helpers


def _set(message: Message, name: str, value: Any) -> None:
    """Store a normalised field value on a frozen dataclass."""
    object.__setattr__(message, name, value)


def _checked_count(owner: str, name: str, value: Any) -> int:
    try:
        count = -1 if isinstance(value, bool) else operator.index(value)
    except TypeError:
        count = -1
    if count < 0:
        raise ProtocolError(f"{owner}: {name} must be a non-negative integer")
    return count


def _checked_step(owner: str, t: Any) -> int:
    return _checked_count(owner, "t", t)


def _checked_number(owner: str, name: str, value: Any, maximum: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ProtocolError(f"{owner}: {name} must be a number")
    number = float(value)
    if not (math.isfinite(number) and 0 <= number <= maximum):
        raise ProtocolError(f"{owner}: {name} = {number} is outside [0, {maximum}]")
    return number


def _checked_cell(owner: str, name: str, cell: Any) -> tuple[int, int]:
    try:
        row, col = (_checked_count(owner, name, v) for v in cell)
    except (TypeError, ValueError):
        raise ProtocolError(f"{owner}: {name} must be two non-negative integers") from None
    return row, col


def _checked_cells(owner: str, name: str, cells: Any) -> np.ndarray:
    """Integer cells (k, 2), non-negative, as int32 (an empty list is k = 0)."""
    array = np.asarray(cells)
    if array.size == 0:
        array = array.reshape(0, 2).astype(np.int32)
    if array.dtype.kind not in "iu" or array.ndim != 2 or array.shape[1] != 2:
        raise ProtocolError(
            f"{owner}: {name} must be integer cells (k, 2), got {array.dtype} {array.shape}"
        )
    if array.size and (array.min() < 0 or array.max() > _INT32_MAX):
        raise ProtocolError(f"{owner}: {name} holds a negative or too large cell index")
    return array.astype(np.int32, copy=False)


def _check_array(owner: str, name: str, array: Any, dtype: type, ndim: int) -> None:
    if not isinstance(array, np.ndarray) or array.dtype != dtype or array.ndim != ndim:
        got = f"{array.dtype} {array.shape}" if isinstance(array, np.ndarray) else type(array)
        wanted = f"a {ndim}-D {np.dtype(dtype)} array"
        raise ProtocolError(f"{owner}: {name} must be {wanted}, got {got}")


def _check_map(owner: str, name: str, array: Any, dtype: type) -> None:
    _check_array(owner, name, array, dtype, 2)
    if min(array.shape) < 1:
        raise ProtocolError(f"{owner}: {name} map of shape {array.shape} is empty")


def _check_codes(owner: str, name: str, observed: np.ndarray) -> None:
    if observed.max() > OCCUPIED:
        raise ProtocolError(f"{owner}: {name} holds codes other than free, unknown, occupied")


def _one_line(owner: str, name: str, text: Any) -> str:
    if not isinstance(text, str):
        raise ProtocolError(f"{owner}: {name} must be a string")
    return " ".join(text.split())
