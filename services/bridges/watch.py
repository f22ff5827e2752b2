"""Watch one robot of a run live: a PNG re-rendered as frames arrive, optionally a GIF at the end.

    python -m services.watch --run RUN [--robot r0] [--png watch.png] [--gif FILE.gif]
        [--every-s 1.0] [--until-finished] [--timeout-s N] [--mode ...] [--connect ...]

The example of an outside tool: it subscribes to the robot's keys and asks each once with a
`get`, so a watch started mid-run shows the current state at once. What it draws, when it
exits and with which status: docs/interop.md#a-png-of-one-robot-servicesbridgeswatch. The
drawing itself (no Zenoh) is in `services.bridges.watch_render`.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import zenoh

from mapex.exit_codes import EXIT_USAGE
from services.bridges.follow import FINAL_STATES, decode_topic
from services.bridges.watch_render import DEFAULT_WATCH, FrameReel, render_frame, write_atomic
from services.codec import ProtocolError
from services.config import WatchConfig
from services.keys import (
    ID_MAX_CHARS,
    RobotKey,
    is_valid_id,
    parse_key,
    robot_key,
    robot_key_pattern,
    run_id_problem,
)
from services.messages import (
    FrontiersMessage,
    GoalMessage,
    MapMessage,
    Message,
    MetricsMessage,
    PathMessage,
    PoseMessage,
    StatusMessage,
)
from services.serving import configure_logging, positive_number, stop_on_signals
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)

EXIT_NOT_FINISHED = 1  # --until-finished, but --timeout-s came first

# topic -> (its message type, WatchState field); decoded by services.bridges.follow.decode_topic
WATCHED_TOPICS: dict[str, tuple[type[Message], str]] = {
    "observed_map": (MapMessage, "observed"),
    "prediction/mean": (MapMessage, "mean"),
    "prediction/variance": (MapMessage, "variance"),
    "pose": (PoseMessage, "pose"),
    "frontiers": (FrontiersMessage, "frontiers"),
    "goal": (GoalMessage, "goal"),
    "path": (PathMessage, "path"),
    "status": (StatusMessage, "status"),
    "metrics": (MetricsMessage, "metrics"),
}
TEAMMATE_TOPICS = ("pose", "goal", "path")  # what the watch draws of the other robots
Ended = Literal["stopped", "finished", "timeout"]

log = logging.getLogger("services.watch")


# ---------------------------------------------------------------------------- state and decoding


@dataclass
class WatchState:
    """The latest message of each watched topic of one robot (None: not heard of yet)."""

    run: str
    robot: str
    observed: MapMessage | None = None
    mean: MapMessage | None = None
    variance: MapMessage | None = None
    pose: PoseMessage | None = None
    frontiers: FrontiersMessage | None = None
    goal: GoalMessage | None = None
    path: PathMessage | None = None
    status: StatusMessage | None = None
    metrics: MetricsMessage | None = None
    received: dict[str, int] = field(default_factory=dict)  # messages applied, by topic
    # robot -> topic -> its latest pose, goal and path (the other robots of a team run)
    teammates: dict[str, dict[str, Message]] = field(default_factory=dict)

    def apply_teammate(self, robot: str, topic: str, message: Message) -> None:
        """Make `message` the latest `topic` (pose, goal or path) of teammate `robot`."""
        self.teammates.setdefault(robot, {})[topic] = message

    def apply(self, topic: str, message: Message) -> None:
        """Make `message` (decoded by `decode_topic`) the latest of `topic`."""
        setattr(self, WATCHED_TOPICS[topic][1], message)
        self.received[topic] = self.received.get(topic, 0) + 1

    @property
    def finished(self) -> bool:
        """Whether the run's status says it finished or failed."""
        return self.status is not None and self.status.state in FINAL_STATES

    @property
    def t(self) -> int | None:
        """The latest step any received message is about."""
        steps = [m.t for m in self._messages() if m is not None]
        return max(steps) if steps else None

    def _messages(self) -> list[Message | None]:
        return [getattr(self, name) for _, name in WATCHED_TOPICS.values()]


def apply_payloads(
    state: WatchState, payloads: dict[str, list[bytes]], keys: dict[str, str]
) -> bool:
    """Apply the newest well-formed payload of each topic (oldest first in each list); log and
    drop malformed ones. True if any applied."""
    applied = False
    for topic, candidates in payloads.items():
        message = _newest_well_formed(topic, candidates, keys[topic])
        if message is not None:
            state.apply(topic, message)
            applied = True
    return applied


def apply_teammates(state: WatchState, payloads: dict[tuple[str, str], bytes]) -> bool:
    """Apply each teammate's newest pose, goal and path; log and drop malformed ones."""
    applied = False
    for (robot, topic), payload in sorted(payloads.items()):
        try:
            state.apply_teammate(robot, topic, decode_topic(topic, payload))
            applied = True
        except ProtocolError as error:
            log.warning("dropped a malformed message of %s on %s: %s", robot, topic, error)
    return applied


def _newest_well_formed(topic: str, candidates: list[bytes], key: str) -> Message | None:
    """The newest of `candidates` that decodes as `topic`'s message; newer malformed ones logged."""
    for payload in reversed(candidates):
        try:
            return decode_topic(topic, payload)
        except ProtocolError as error:
            log.warning("dropped a malformed message on %s: %s", key, error)
    return None


# ---------------------------------------------------------------------------- outputs


class FrameOutputs:
    """Where rendered frames go: the PNG (each one) and, with a GIF path, the reel."""

    def __init__(self, png: Path, gif: Path | None, config: WatchConfig) -> None:
        self.png, self.gif, self.config = png, gif, config
        self.reel = FrameReel(config.max_gif_frames, config.gif_max_side_px) if gif else None
        self.rendered = 0

    def render(self, state: WatchState, final: bool = False) -> None:
        """Render `state`, rewrite the PNG, keep the frame for the GIF."""
        png = render_frame(state, self.config)
        try:
            write_atomic(self.png, png)
        except OSError as error:
            log.warning("could not write %s: %s", self.png, error)
        if self.reel is not None:
            self.reel.add(png, force=final)
        self.rendered += 1

    def close(self) -> None:
        """Write the GIF, if one was asked for and any frame was rendered."""
        if self.reel is None or self.gif is None:
            return
        if not self.reel.frames:
            log.warning("no frame was rendered: %s not written", self.gif)
            return
        try:
            write_atomic(self.gif, self.reel.gif_bytes(self.config.gif_frame_ms))
        except OSError as error:
            log.error("could not write %s: %s", self.gif, error)
            return
        log.info("wrote %s (%d frames)", self.gif, len(self.reel.frames))


# ---------------------------------------------------------------------------- Zenoh glue


class Inbox:
    """The newest raw payloads per topic, filled on Zenoh's threads, drained by the main loop.

    Up to `depth` payloads per topic are kept between drains, so that a malformed payload
    arriving just after a good one (say, after the final status) does not hide it."""

    def __init__(self, depth: int = DEFAULT_WATCH.inbox_depth) -> None:
        self._lock = threading.Lock()
        self._depth = depth
        self._pending: dict[str, deque[bytes]] = {}
        self._heard: set[str] = set()

    def deliver(self, topic: str, payload: bytes) -> None:
        """A live sample: the newest of `topic`."""
        with self._lock:
            self._pending.setdefault(topic, deque(maxlen=self._depth)).append(payload)
            self._heard.add(topic)

    def offer(self, topic: str, payload: bytes) -> None:
        """A late-joiner reply: taken only if no live sample of `topic` came first (newer)."""
        with self._lock:
            if topic not in self._heard:
                self._pending[topic] = deque([payload], maxlen=self._depth)
                self._heard.add(topic)

    def drain(self) -> dict[str, list[bytes]]:
        """The pending payloads of each topic, oldest first, emptying the inbox."""
        with self._lock:
            pending, self._pending = self._pending, {}
        return {topic: list(payloads) for topic, payloads in pending.items()}

    def unheard(self) -> list[str]:
        """The watched topics nothing has arrived on yet."""
        with self._lock:
            return [topic for topic in WATCHED_TOPICS if topic not in self._heard]


class Watcher:
    """Subscribers on one robot's watched keys feeding an `Inbox`, and late-joiner queries;
    subscribers on every robot's pose, goal and path for the teammates."""

    def __init__(self, session: zenoh.Session, run: str, robot: str, config: WatchConfig) -> None:
        self.session, self.config, self.robot = session, config, robot
        self.keys = {topic: robot_key(run, robot, topic) for topic in WATCHED_TOPICS}
        self.inbox = Inbox(config.inbox_depth)
        self._teammates: dict[tuple[str, str], bytes] = {}  # (robot, topic) -> newest payload
        self._teammates_lock = threading.Lock()
        # subscribe first, then ask: nothing put in between is missed
        self.subscribers = [
            session.declare_subscriber(key, self._on_sample(topic))
            for topic, key in self.keys.items()
        ]
        self.subscribers += [
            session.declare_subscriber(robot_key_pattern(topic, run), self._on_teammate)
            for topic in TEAMMATE_TOPICS
        ]
        self._next_ask_s = 0.0
        self.ask_unheard(time.monotonic())

    def ask_unheard(self, now_s: float) -> None:
        """`get` the topics nothing has arrived on, at most once per `get_timeout_s`."""
        if now_s < self._next_ask_s:
            return
        self._next_ask_s = now_s + self.config.get_timeout_s
        for topic in self.inbox.unheard():
            self.session.get(
                self.keys[topic], self._on_reply(topic), timeout=self.config.get_timeout_s
            )

    def close(self) -> None:
        """Undeclare the subscribers (replies still in flight are dropped with the session)."""
        for subscriber in self.subscribers:
            subscriber.undeclare()

    def drain_teammates(self) -> dict[tuple[str, str], bytes]:
        """The newest payload of each (teammate, topic) since the last drain."""
        with self._teammates_lock:
            pending, self._teammates = self._teammates, {}
        return pending

    def _on_teammate(self, sample: zenoh.Sample) -> None:
        try:
            key = parse_key(str(sample.key_expr))
        except ProtocolError as error:
            log.warning("dropped a teammate message: %s", error)
            return
        if isinstance(key, RobotKey) and key.robot != self.robot:
            with self._teammates_lock:
                self._teammates[key.robot, key.topic] = sample.payload.to_bytes()

    def _on_sample(self, topic: str):
        return lambda sample: self.inbox.deliver(topic, sample.payload.to_bytes())

    def _on_reply(self, topic: str):
        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                self.inbox.offer(topic, reply.ok.payload.to_bytes())
            else:
                log.warning("query on %s got an error reply", self.keys[topic])

        return on_reply


@dataclass(frozen=True)
class WatchSummary:
    """How a watch ended and how many frames it rendered."""

    ended: Ended
    frames: int


def main(
    config: zenoh.Config,
    run: str,
    robot: str = "r0",
    png: Path = Path("watch.png"),
    gif: Path | None = None,
    every_s: float | None = None,
    until_finished: bool = False,
    timeout_s: float | None = None,
    stop: threading.Event | None = None,
    watch: WatchConfig = DEFAULT_WATCH,
) -> WatchSummary:
    """Watch robot `robot` of `run` until `stop`, the run's end (`until_finished`) or `timeout_s`.

    Raises ZenohConfigError when the session is refused.
    """
    deadline_s = None if timeout_s is None else time.monotonic() + timeout_s
    outputs = FrameOutputs(Path(png), None if gif is None else Path(gif), watch)
    session = open_session(config)
    try:
        watcher = Watcher(session, run, robot, watch)
        log.info("watching run %s robot %s into %s", run, robot, png)
        try:
            state = WatchState(run, robot)
            ended = _loop(
                watcher,
                state,
                outputs,
                stop or threading.Event(),
                deadline_s,
                every_s or watch.every_s,
                until_finished,
            )
        finally:
            watcher.close()
    finally:
        session.close()
        outputs.close()
    received = ", ".join(f"{topic} {n}" for topic, n in sorted(state.received.items()))
    log.info("stopped (%s) after %d frames; received %s", ended, outputs.rendered, received)
    return WatchSummary(ended, outputs.rendered)


def _loop(
    watcher: Watcher,
    state: WatchState,
    outputs: FrameOutputs,
    stop: threading.Event,
    deadline_s: float | None,
    every_s: float,
    until_finished: bool,
) -> Ended:
    """Apply arrivals, render at most every `every_s`; return why the watch ended."""
    next_render_s, dirty = time.monotonic(), False
    while True:
        dirty |= apply_payloads(state, watcher.inbox.drain(), watcher.keys)
        dirty |= apply_teammates(state, watcher.drain_teammates())
        now_s = time.monotonic()
        ended = _ended(stop, state, until_finished, deadline_s, now_s)
        if ended is not None:
            break
        if dirty and now_s >= next_render_s:
            outputs.render(state)
            dirty, next_render_s = False, now_s + every_s
        watcher.ask_unheard(now_s)
        stop.wait(watcher.config.poll_s)
    if dirty:
        outputs.render(state, final=True)
    return ended


def _ended(
    stop: threading.Event,
    state: WatchState,
    until_finished: bool,
    deadline_s: float | None,
    now_s: float,
) -> Ended | None:
    if stop.is_set():
        return "stopped"
    if until_finished and state.finished:
        return "finished"
    if deadline_s is not None and now_s >= deadline_s:
        return "timeout"
    return None


# ---------------------------------------------------------------------------- command line


def build_parser() -> argparse.ArgumentParser:
    """The command-line flags: run, robot, outputs, timing and Zenoh's."""
    parser = argparse.ArgumentParser(
        prog="python -m services.watch", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--run", required=True, help="run id, the <run> chunk of the keys")
    parser.add_argument("--robot", default="r0", help="robot id to watch (default: %(default)s)")
    parser.add_argument(
        "--png",
        type=Path,
        default=Path("watch.png"),
        help="PNG rewritten with each frame (default: %(default)s)",
    )
    parser.add_argument("--gif", type=Path, default=None, help="write an animated GIF on exit")
    parser.add_argument(
        "--every-s",
        type=positive_number("of seconds"),
        default=DEFAULT_WATCH.every_s,
        help="render at most this often, in seconds (default: %(default)s)",
    )
    parser.add_argument(
        "--until-finished",
        action="store_true",
        help="exit when the run's status says finished or failed",
    )
    parser.add_argument(
        "--timeout-s",
        type=positive_number("of seconds"),
        default=None,
        help="stop after this many seconds (exit 1 if --until-finished and not finished)",
    )
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    """Parse flags, watch; 0 on a clean stop, 1 on --until-finished timing out, 2 on bad flags."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_flags(parser, args)
    configure_logging(f"watch[{args.run}/{args.robot}]")
    stop = stop_on_signals()
    try:
        config = zenoh_config_from_args(args)
        summary = main(
            config,
            args.run,
            args.robot,
            args.png,
            args.gif,
            args.every_s,
            args.until_finished,
            args.timeout_s,
            stop,
        )
    except ZenohConfigError as error:
        log.error("%s", error)
        return EXIT_USAGE
    if summary.ended == "timeout" and args.until_finished:
        log.error("timed out after %s s before run %s finished", args.timeout_s, args.run)
        return EXIT_NOT_FINISHED
    return 0


def _check_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """argparse-style one-line errors (exit 2) for flag values argparse cannot check itself."""
    if (problem := run_id_problem(args.run)) is not None:
        parser.error(problem)
    if not is_valid_id(args.robot):
        parser.error(f"--robot {args.robot!r} must match [a-z0-9_-]{{1,{ID_MAX_CHARS}}}")
    for flag, path in (("--png", args.png), ("--gif", args.gif)):
        if path is not None and not path.parent.resolve().is_dir():
            parser.error(f"{flag} {str(path)!r}: directory {str(path.parent)!r} does not exist")
        if path is not None and path.is_dir():
            parser.error(f"{flag} {str(path)!r} is a directory")


if __name__ == "__main__":
    sys.exit(run_cli())
