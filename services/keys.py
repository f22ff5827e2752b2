"""Version-1 key expressions: where things are published, built and parsed only here.

Per robot of a run `mapex/@v1/<run>/<robot>/<topic>` for each topic of `ROBOT_TOPICS`, per
run `mapex/@v1/<run>/<topic>` for each of `RUN_TOPICS`, the predictor queryables and health
probes `mapex/@v1/{predict,health}/<member>/<worker_id>` and the liveliness tokens under
`mapex/@v1/alive/`. Run, robot and worker ids match `[a-z0-9_-]{1,ID_MAX_CHARS}`; "predict",
"health" and "alive" are not run ids. Every key and what it carries: docs/protocol.md.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal, get_args

from mapex.prediction.base import MEMBER_NAMES
from services.codec import ProtocolError

KEY_PREFIX = "mapex/@v1"

MEMBERS = MEMBER_NAMES  # ensemble members; "g" is G
RESERVED_RUN_IDS = frozenset({"predict", "health", "alive"})
ROBOT_ID_PREFIX = "r"  # robot i of a run is "r<i>" in its keys
ID_MAX_CHARS = 64  # part of the v1 contract, not a tunable
_ID_PATTERN = re.compile(rf"[a-z0-9_-]{{1,{ID_MAX_CHARS}}}")

RobotTopic = Literal[
    "step",
    "pose",
    "scan",
    "observed_map",
    "prediction/main",
    "prediction/mean",
    "prediction/variance",
    "frontiers",
    "goal",
    "path",
    "metrics",
    "status",
]
RunTopic = Literal["ground_truth", "world_info"]
ROBOT_TOPICS: tuple[str, ...] = get_args(RobotTopic)
RUN_TOPICS: tuple[str, ...] = get_args(RunTopic)


@dataclass(frozen=True)
class RobotKey:
    """A parsed `mapex/@v1/<run>/<robot>/<topic>`."""

    run: str
    robot: str
    topic: str


@dataclass(frozen=True)
class RunKey:
    """A parsed `mapex/@v1/<run>/<topic>` (ground truth, world info)."""

    run: str
    topic: str


@dataclass(frozen=True)
class PredictKey:
    """A parsed `mapex/@v1/predict/<member>/<worker_id>`."""

    member: str
    worker_id: str


@dataclass(frozen=True)
class HealthKey:
    """A parsed `mapex/@v1/health/<member>/<worker_id>`."""

    member: str
    worker_id: str


@dataclass(frozen=True)
class AliveKey:
    """A parsed liveliness key; `run` for world/planner (and `robot` for a planner),
    `member` and `worker_id` for predict."""

    role: str
    run: str | None = None
    member: str | None = None
    worker_id: str | None = None
    robot: str | None = None


ParsedKey = RobotKey | RunKey | PredictKey | HealthKey | AliveKey


def is_valid_id(value: object) -> bool:
    """Whether `value` may be a run, robot or worker id (one key chunk, no wildcard)."""
    return isinstance(value, str) and _ID_PATTERN.fullmatch(value) is not None


def robot_id(robot: int) -> str:
    """The wire id of robot index `robot`: `r0`, `r1`, ..."""
    return f"{ROBOT_ID_PREFIX}{robot}"


def robot_key(run: str, robot: str, topic: RobotTopic) -> str:
    """`mapex/@v1/<run>/<robot>/<topic>`."""
    return f"{KEY_PREFIX}/{_run_id(run)}/{_id(robot, 'robot')}/{_choice(topic, ROBOT_TOPICS)}"


def robot_key_pattern(topic: RobotTopic, run: str | None = None, robot: str | None = None) -> str:
    """The key of `topic` with `*` for the run and/or robot left as None (for subscribers)."""
    run_chunk = "*" if run is None else _run_id(run)
    robot_chunk = "*" if robot is None else _id(robot, "robot")
    return f"{KEY_PREFIX}/{run_chunk}/{robot_chunk}/{_choice(topic, ROBOT_TOPICS)}"


def run_key(run: str, topic: RunTopic) -> str:
    """`mapex/@v1/<run>/ground_truth` or `mapex/@v1/<run>/world_info`."""
    return f"{KEY_PREFIX}/{_run_id(run)}/{_choice(topic, RUN_TOPICS)}"


def predict_key(member: str, worker_id: str) -> str:
    """The queryable of one predictor worker: `mapex/@v1/predict/<member>/<worker_id>`."""
    return f"{KEY_PREFIX}/predict/{_choice(member, MEMBERS)}/{_id(worker_id, 'worker')}"


def health_key(member: str, worker_id: str) -> str:
    """The health probe of one predictor worker: `mapex/@v1/health/<member>/<worker_id>`."""
    return f"{KEY_PREFIX}/health/{_choice(member, MEMBERS)}/{_id(worker_id, 'worker')}"


def alive_predictor_key(member: str, worker_id: str) -> str:
    """Liveliness token of a predictor worker."""
    return f"{KEY_PREFIX}/alive/predict/{_choice(member, MEMBERS)}/{_id(worker_id, 'worker')}"


def alive_predictor_pattern(member: str | None = None) -> str:
    """All workers' liveliness tokens, of one member or (None) of every member."""
    member_chunk = "*" if member is None else _choice(member, MEMBERS)
    return f"{KEY_PREFIX}/alive/predict/{member_chunk}/*"


def alive_world_key(run: str) -> str:
    """Liveliness token of the world serving `run`."""
    return f"{KEY_PREFIX}/alive/world/{_run_id(run)}"


def alive_planner_key(run: str, robot: str) -> str:
    """Liveliness token of the planner of robot `robot` of `run`."""
    return f"{KEY_PREFIX}/alive/planner/{_run_id(run)}/{_id(robot, 'robot')}"


def alive_planner_pattern(run: str) -> str:
    """The liveliness tokens of every planner of `run`."""
    return f"{KEY_PREFIX}/alive/planner/{_run_id(run)}/*"


def parse_key(key: str) -> ParsedKey:
    """Split a MapEx v1 key (e.g. one a wildcard subscriber received) into its parts."""
    prefix, _, rest = str(key).partition(f"{KEY_PREFIX}/")
    chunks = rest.split("/")
    parsed = None if prefix else _parse_chunks(chunks)
    if parsed is None:
        raise ProtocolError(f"key '{key}' is not a MapEx v1 key")
    return parsed


def _parse_chunks(chunks: list[str]) -> ParsedKey | None:
    head, n = chunks[0], len(chunks)
    worker = n == 3 and chunks[1] in MEMBERS and is_valid_id(chunks[2])
    if head in ("predict", "health") and worker:
        return (PredictKey if head == "predict" else HealthKey)(chunks[1], chunks[2])
    if head == "alive":
        return _parse_alive(chunks[1:])
    if not _is_run_id(head):
        return None
    if n == 2 and chunks[1] in RUN_TOPICS:
        return RunKey(head, chunks[1])
    topic = "/".join(chunks[2:])
    if n in (3, 4) and is_valid_id(chunks[1]) and topic in ROBOT_TOPICS:
        return RobotKey(head, chunks[1], topic)
    return None


def _parse_alive(chunks: list[str]) -> AliveKey | None:
    role, ids = chunks[0], chunks[1:]
    if role == "predict" and len(ids) == 2 and ids[0] in MEMBERS and is_valid_id(ids[1]):
        return AliveKey(role, member=ids[0], worker_id=ids[1])
    if role == "world" and len(ids) == 1 and _is_run_id(ids[0]):
        return AliveKey(role, run=ids[0])
    if role == "planner" and len(ids) == 2 and _is_run_id(ids[0]) and is_valid_id(ids[1]):
        return AliveKey(role, run=ids[0], robot=ids[1])
    return None


def run_id_problem(run: str, flag: str = "--run") -> str | None:
    """Why `run` cannot name a run, as a one-line message naming `flag`; None when it can."""
    if _is_run_id(run):
        return None
    return (
        f"{flag} {run!r} must match [a-z0-9_-]{{1,{ID_MAX_CHARS}}} "
        f"and not be {' or '.join(sorted(RESERVED_RUN_IDS))}"
    )


def _is_run_id(value: str) -> bool:
    return is_valid_id(value) and value not in RESERVED_RUN_IDS


def _id(value: str, what: str) -> str:
    if not is_valid_id(value):
        raise ValueError(f"{what} id {value!r} must match {_ID_PATTERN.pattern}")
    return value


def _run_id(value: str) -> str:
    if value in RESERVED_RUN_IDS:
        raise ValueError(f"run id {value!r} is reserved (clashes with a key of the protocol)")
    return _id(value, "run")


def _choice(value: str, allowed: tuple[str, ...]) -> str:
    if value not in allowed:
        raise ValueError(f"{value!r} is not one of {', '.join(allowed)}")
    return value
