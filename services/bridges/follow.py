"""Follow every robot of one run, or of every run, for the outside-tool bridges.

The ROS 2 bridge, the MCAP recorder and the browser view all need each robot's maps, pose,
path, goal, frontiers, metrics and status as they are published, plus each run's world
info, for runs that start later too; the ROS translation also each robot's scan (asked for
with `topics=`: a whole scan per robot per step, which the other sinks do without).
`RunFollower` subscribes with wildcards (`mapex/@v1/<run or *>/*/<topic>`), asks once with
a `get` for what was published before it joined, decodes on Zenoh's threads and hands
`Update`s to one consumer thread, so a sink never needs a lock. Compare steps per topic,
never across topics (docs/protocol.md). A payload that does not decode, or a key that is
not a MapEx v1 key, is dropped with one log line.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from services.codec import ProtocolError
from services.keys import RobotKey, parse_key, robot_key_pattern, run_key
from services.messages import (
    FrontiersMessage,
    GoalMessage,
    MapMessage,
    Message,
    MetricsMessage,
    PathMessage,
    PoseMessage,
    ScanReply,
    StatusMessage,
    WorldInfo,
    decode_message,
)

# topic -> the message it carries (the maps' kind is checked too)
FOLLOWED_TOPICS: dict[str, type[Message]] = {
    "observed_map": MapMessage,
    "prediction/mean": MapMessage,
    "prediction/variance": MapMessage,
    "pose": PoseMessage,
    "frontiers": FrontiersMessage,
    "goal": GoalMessage,
    "path": PathMessage,
    "status": StatusMessage,
    "metrics": MetricsMessage,
    "scan": ScanReply,
}
OPT_IN_TOPICS = ("scan",)  # followed only when a sink asks for them (topics=)
DEFAULT_TOPICS: tuple[str, ...] = tuple(t for t in FOLLOWED_TOPICS if t not in OPT_IN_TOPICS)
MAP_KIND_OF_TOPIC = {
    "observed_map": "observed",
    "prediction/mean": "mean",
    "prediction/variance": "variance",
}
FINAL_STATES = ("finished", "failed")  # a robot's run is over once its status says one
WORLD_INFO_TOPIC = "world_info"  # an Update with robot None carries the run's WorldInfo

log = logging.getLogger("services.follow")


@dataclass(frozen=True)
class Update:
    """One decoded message of a run: `robot` None for the run's world info."""

    run: str
    robot: str | None
    topic: str
    message: Message


Sink = Callable[[Update], None]


def decode_topic(topic: str, payload: bytes) -> Message:
    """The message of a payload received on `topic`; ProtocolError when it is not the right
    one (wrong type, or a map of another kind)."""
    message = decode_message(payload, (FOLLOWED_TOPICS[topic],))
    kind = MAP_KIND_OF_TOPIC.get(topic)
    if kind is not None and message.kind != kind:
        raise ProtocolError(f"a map of kind {message.kind!r} on {topic}, expected {kind!r}")
    return message


class RunFollower:
    """Subscribers on the followed topics of `run` (None: every run) feeding `sink` on one
    thread of its own, until `close`."""

    def __init__(
        self,
        session: zenoh.Session,
        sink: Sink,
        run: str | None = None,
        topics: tuple[str, ...] = DEFAULT_TOPICS,
        get_timeout_s: float = 2.0,
    ) -> None:
        unknown = set(topics) - set(FOLLOWED_TOPICS)
        if unknown:
            raise ValueError(f"cannot follow {sorted(unknown)} (choose from {FOLLOWED_TOPICS})")
        self.session, self.sink, self.run = session, sink, run
        self.get_timeout_s = get_timeout_s
        self.received = 0
        self.dropped = 0
        self._queue: queue.Queue[Update | None] = queue.Queue()
        self._runs_seen: set[str] = set()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._deliver, name="follow", daemon=True)
        self._thread.start()
        # subscribe first, then ask: nothing published in between is missed
        self._subscribers = [
            session.declare_subscriber(robot_key_pattern(topic, run), self._on_sample)
            for topic in topics
        ]
        self._subscribers.append(
            session.declare_subscriber(_world_info_pattern(run), self._on_sample)
        )
        for topic in topics:
            session.get(robot_key_pattern(topic, run), self._on_reply, timeout=get_timeout_s)
        session.get(_world_info_pattern(run), self._on_reply, timeout=get_timeout_s)

    def close(self) -> None:
        """Undeclare the subscribers and stop the consumer thread after what is queued."""
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._queue.put(None)
        self._thread.join(timeout=10)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._on_sample(reply.ok)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            update = _decode(key, sample.payload.to_bytes())
        except (ProtocolError, KeyError) as error:
            with self._lock:
                self.dropped += 1
            log.warning("dropped a message on %s: %s", key, error)
            return
        with self._lock:
            self.received += 1
            new_run = update.run not in self._runs_seen
            self._runs_seen.add(update.run)
        self._queue.put(update)
        if new_run and update.topic != WORLD_INFO_TOPIC:
            self.session.get(
                run_key(update.run, WORLD_INFO_TOPIC), self._on_reply, timeout=self.get_timeout_s
            )

    def _deliver(self) -> None:
        while (update := self._queue.get()) is not None:
            try:
                self.sink(update)
            except Exception:  # a sink's bug must not stop the follower; say where it was
                log.exception("the sink failed on %s of %s", update.topic, update.run)


def _world_info_pattern(run: str | None) -> str:
    return run_key(run, WORLD_INFO_TOPIC) if run else "mapex/@v1/*/world_info"


def _decode(key: str, payload: bytes) -> Update:
    parsed = parse_key(key)
    if isinstance(parsed, RobotKey):
        if parsed.topic not in FOLLOWED_TOPICS:
            raise ProtocolError(f"topic {parsed.topic} is not followed")
        return Update(parsed.run, parsed.robot, parsed.topic, decode_topic(parsed.topic, payload))
    if getattr(parsed, "topic", None) == WORLD_INFO_TOPIC:
        info = decode_message(payload, (WorldInfo,))
        return Update(parsed.run, None, WORLD_INFO_TOPIC, info)
    raise ProtocolError(f"key {key} is not a followed topic")
