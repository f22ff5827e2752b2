"""What the browser view (`services.web`) knows and sends: the state of the followed runs
and the server-sent events made of it, with no HTTP and no Zenoh in it.

`ViewState` keeps, per run and robot, the latest message of each topic, the metric history
and the trajectory, for the snapshot a page starts from; `encode_update` turns one update
into the JSON of its event (maps as base64 of their uint8 cells); `MapThrottle` thins map
events per robot and kind, always letting the newest through; `RunRecord.final` says how a
run ended once every robot of it said so; `EventClient` is one browser's queue of frames,
bounded in frames and bytes, where a newer map replaces the older one still queued
(`frame_key`: latest wins).
"""

from __future__ import annotations

import base64
import json
import logging
import math
import threading
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.bridges.follow import FINAL_STATES, MAP_KIND_OF_TOPIC, Update
from services.config import DEFAULT_WEB, WebConfig
from services.messages import (
    FrontiersMessage,
    GoalMessage,
    MapMessage,
    Message,
    MetricsMessage,
    PathMessage,
    PoseMessage,
    StatusMessage,
    WorldInfo,
)

KEEPALIVE_FRAME = b": keep-alive\n\n"
FINISHED, FAILED = FINAL_STATES

log = logging.getLogger("services.web")


# ---------------------------------------------------------------------------- event encoding


def _cells(cells: Any) -> list[list[int]]:
    """(row, col) cells, an int array (k, 2) or a list of pairs, as JSON lists."""
    return np.asarray(cells, dtype=np.int64).reshape(-1, 2).tolist()


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _encode_map(message: MapMessage) -> dict[str, Any]:
    rows, cols = message.map_u8.shape
    data = base64.b64encode(message.map_u8.tobytes(order="C")).decode("ascii")
    return {"t": message.t, "kind": message.kind, "width": cols, "height": rows, "data": data}


_ENCODERS: dict[type[Message], Callable[[Any], dict[str, Any]]] = {
    MapMessage: _encode_map,
    PoseMessage: lambda m: {"t": m.t, "pose": [int(m.pose[0]), int(m.pose[1])]},
    FrontiersMessage: lambda m: {
        "t": m.t,
        "cells": _cells(m.cells),
        "scores": [_finite_or_none(s) for s in m.scores.tolist()],
    },
    GoalMessage: lambda m: {"t": m.t, "goal": None if m.goal is None else _cells([m.goal])[0]},
    PathMessage: lambda m: {"t": m.t, "cells": _cells(m.cells)},
    StatusMessage: lambda m: {"t": m.t, "state": m.state, "detail": m.detail},
    MetricsMessage: lambda m: {
        "t": m.t,
        "coverage": m.coverage,
        "iou": m.iou,
        "tu": m.tu,
        "degraded": m.degraded,
    },
    WorldInfo: lambda m: {
        "name": m.name,
        "shape": [int(m.shape[0]), int(m.shape[1])],
        "resolution_m": m.resolution_m,
    },
}


def encode_update(update: Update) -> dict[str, Any]:
    """The JSON-able event of an update: run, robot, topic, then the message's fields (the
    table of docs/protocol.md#the-browser-view-http-routes-and-sse-events). Non-finite
    frontier scores become null."""
    head = {"run": update.run, "robot": update.robot, "topic": update.topic}
    return {**head, **_ENCODERS[type(update.message)](update.message)}


def sse_frame(event: str, data: dict[str, Any]) -> bytes:
    """One Server-Sent Events frame: `event: NAME`, one `data:` line of compact JSON."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False)
    return f"event: {event}\ndata: {text}\n\n".encode()


def final_event(run: str, final: dict[str, Any] | None) -> dict[str, Any]:
    """The data of a `final` event: how `run` ended (`RunRecord.final`), null again when a
    robot that has not ended joined it."""
    return {"run": run, "final": final}


def frame_key(update: Update) -> tuple[str, str | None, str] | None:
    """The key under which `update`'s event replaces an older one still queued for a slow
    stream (`EventClient`): (run, robot, topic) for a map (`MAP_KIND_OF_TOPIC`: the large
    events, whose newest is all a page draws), None for every other topic (small events,
    each of which a page keeps: a pose extends the trajectory, a status may end the run)."""
    return (update.run, update.robot, update.topic) if update.topic in MAP_KIND_OF_TOPIC else None


def _step(update: Update) -> int | None:
    return getattr(update.message, "t", None)


# ---------------------------------------------------------------------------- throttling


ThrottleKey = tuple[str, str | None, str]  # (run, robot, topic)


class MapThrottle:
    """At most one map per `min_interval_s` per (run, robot, topic); the newest always gets out.

    `offer` says whether an update may go now; one that may not is held back, replacing any
    older one held for its key, and `due` hands it over once its key's interval has passed.
    Times are passed in (monotonic seconds) so the class is pure and testable.
    """

    def __init__(self, min_interval_s: float) -> None:
        self.min_interval_s = min_interval_s
        self._last_sent_s: dict[ThrottleKey, float] = {}
        self._held: dict[ThrottleKey, Update] = {}

    def offer(self, update: Update, now_s: float) -> Update | None:
        """`update` if it may be sent now (the caller sends it), else None (it is held)."""
        key = (update.run, update.robot, update.topic)
        if self._may_send(key, now_s):
            self._last_sent_s[key] = now_s
            self._held.pop(key, None)
            return update
        self._held[key] = update
        return None

    def due(self, now_s: float) -> list[Update]:
        """The held updates whose interval has passed (the caller sends them), in key order."""
        ready = [key for key in self._held if self._may_send(key, now_s)]
        for key in ready:
            self._last_sent_s[key] = now_s
        return [self._held.pop(key) for key in ready]

    def held(self) -> int:
        """How many updates are held back."""
        return len(self._held)

    def _may_send(self, key: ThrottleKey, now_s: float) -> bool:
        last_s = self._last_sent_s.get(key)
        return last_s is None or now_s - last_s >= self.min_interval_s


# ---------------------------------------------------------------------------- what is known


@dataclass
class RobotRecord:
    """What is known of one robot: the latest update per topic, its metric samples and poses."""

    latest: dict[str, Update] = field(default_factory=dict)
    metrics_history: deque[dict[str, Any]] = field(default_factory=deque)
    trajectory: deque[tuple[int, int]] = field(default_factory=deque)

    @property
    def t(self) -> int | None:
        """The latest step any known message of this robot is about."""
        steps = [step for step in map(_step, self.latest.values()) if step is not None]
        return max(steps) if steps else None


@dataclass
class RunRecord:
    """What is known of one run: its world info and its robots."""

    world: Update | None = None
    robots: dict[str, RobotRecord] = field(default_factory=dict)

    @property
    def final(self) -> dict[str, Any] | None:
        """How the run ended, once every robot known of it said finished or failed:
        `{"state": "failed" if any failed else "finished", "t": the latest of their steps}`;
        None before (a robot without a final status, or no robot yet)."""
        statuses = [robot.latest.get("status") for robot in self.robots.values()]
        if not statuses or any(
            status is None or status.message.state not in FINAL_STATES for status in statuses
        ):
            return None
        failed = any(status.message.state == FAILED for status in statuses)
        return {
            "state": FAILED if failed else FINISHED,
            "t": max(status.message.t for status in statuses),
        }


class ViewState:
    """Everything the view knows, for `/state` and a new stream's snapshot. Not thread-safe:
    `WebView` holds its lock around every call."""

    def __init__(self, config: WebConfig = DEFAULT_WEB, followed_run: str | None = None) -> None:
        self.config = config
        self.followed_run = followed_run
        self.runs: OrderedDict[str, RunRecord] = OrderedDict()  # least recently updated first

    def apply(self, update: Update) -> bool:
        """Take `update` in; False (and nothing changes) when it is older than the known one."""
        run = self._run(update.run)
        if update.robot is None:
            run.world = update
            return True
        robot = run.robots.setdefault(update.robot, self._new_robot())
        known = robot.latest.get(update.topic)
        if known is not None and _step(update) < _step(known):
            return False
        robot.latest[update.topic] = update
        self._accumulate(robot, update.message)
        return True

    def final(self, run: str) -> dict[str, Any] | None:
        """How `run` ended (`RunRecord.final`); None while it goes on or when it is unknown."""
        record = self.runs.get(run)
        return None if record is None else record.final

    def snapshot(self) -> dict[str, Any]:
        """The `/state` document (docs/protocol.md#the-browser-view-http-routes-and-sse-events)."""
        return {
            "followed_run": self.followed_run,
            "runs": {name: self._run_snapshot(run) for name, run in self.runs.items()},
        }

    def _run(self, name: str) -> RunRecord:
        if name not in self.runs:
            self.runs[name] = RunRecord()
            while len(self.runs) > self.config.max_runs:
                forgotten, _ = self.runs.popitem(last=False)
                log.info("forgot run %s (more than %d runs)", forgotten, self.config.max_runs)
        self.runs.move_to_end(name)
        return self.runs[name]

    def _new_robot(self) -> RobotRecord:
        return RobotRecord(
            metrics_history=deque(maxlen=self.config.max_metric_points),
            trajectory=deque(maxlen=self.config.max_trajectory_points),
        )

    @staticmethod
    def _accumulate(robot: RobotRecord, message: Message) -> None:
        """Extend the metric history and the trajectory with a new sample or a moved pose."""
        if isinstance(message, MetricsMessage):
            history = robot.metrics_history
            if not history or message.t > history[-1]["t"]:
                history.append(_ENCODERS[MetricsMessage](message))
        elif isinstance(message, PoseMessage):
            cell = (int(message.pose[0]), int(message.pose[1]))
            if not robot.trajectory or robot.trajectory[-1] != cell:
                robot.trajectory.append(cell)

    @staticmethod
    def _run_snapshot(run: RunRecord) -> dict[str, Any]:
        return {
            "world": None if run.world is None else encode_update(run.world),
            "final": run.final,
            "robots": {
                name: {
                    "t": robot.t,
                    "latest": {topic: encode_update(u) for topic, u in robot.latest.items()},
                    "metrics_history": list(robot.metrics_history),
                    "trajectory": [list(cell) for cell in robot.trajectory],
                }
                for name, robot in sorted(run.robots.items())
            },
        }


# ---------------------------------------------------------------------------- event clients


class _Queued:
    """One queued frame and the key it may be replaced under (compared by identity)."""

    __slots__ = ("frame", "key")

    def __init__(self, frame: bytes, key: Hashable | None) -> None:
        self.frame, self.key = frame, key


class EventClient:
    """The frames waiting for one `/events` stream, filled by `WebView`, drained by its
    handler thread; its memory is bounded whether or not the browser reads.

    A frame pushed with a `key` (`frame_key`: a robot's map of one kind) replaces the frame
    of that key still queued (latest wins: the older one is dropped, the newer one queued
    last, so the order of the rest is kept).
    Closed when it overflows, `max_queued_events` frames or `max_queued_bytes` bytes (a
    stalled browser: what is queued is dropped; the browser reconnects and starts from a
    fresh snapshot), or when the view closes (what is queued is still sent, e.g. a run's
    final status)."""

    def __init__(
        self, max_queued_events: int, max_queued_bytes: int = DEFAULT_WEB.client_max_queued_bytes
    ) -> None:
        self.max_queued_events, self.max_queued_bytes = max_queued_events, max_queued_bytes
        self.queued_bytes = 0
        self.replaced = 0  # frames dropped for a newer one of their key
        self._frames: deque[_Queued] = deque()
        self._keyed: dict[Hashable, _Queued] = {}
        self._changed = threading.Condition()
        self.closed = False

    def __len__(self) -> int:
        with self._changed:
            return len(self._frames)

    def push(self, frame: bytes, key: Hashable | None = None) -> bool:
        """Queue `frame` (in place of the queued frame of `key`, if any); False (and the
        client is closed) when it is closed or too far behind."""
        with self._changed:
            if not self.closed and key is not None and (older := self._keyed.pop(key, None)):
                self._frames.remove(older)
                self.queued_bytes -= len(older.frame)
                self.replaced += 1
            if not self.closed and (
                len(self._frames) >= self.max_queued_events
                or self.queued_bytes + len(frame) > self.max_queued_bytes
            ):
                self.closed = True
                self._clear()
            if self.closed:
                self._changed.notify_all()
                return False
            queued = _Queued(frame, key)
            self._frames.append(queued)
            if key is not None:
                self._keyed[key] = queued
            self.queued_bytes += len(frame)
            self._changed.notify_all()
            return True

    def close(self, drain: bool = False) -> None:
        """End the stream: no frame is taken from now on; `next_frame` returns None at once,
        or, with `drain`, once the frames already queued are taken."""
        with self._changed:
            self.closed = True
            if not drain:
                self._clear()
            self._changed.notify_all()

    def next_frame(self, timeout_s: float) -> bytes | None:
        """The next frame; KEEPALIVE_FRAME after `timeout_s` without one; None once closed
        and drained."""
        with self._changed:
            self._changed.wait_for(lambda: self._frames or self.closed, timeout_s)
            if self._frames:
                queued = self._frames.popleft()
                if queued.key is not None:
                    del self._keyed[queued.key]
                self.queued_bytes -= len(queued.frame)
                return queued.frame
            return None if self.closed else KEEPALIVE_FRAME

    def _clear(self) -> None:
        self._frames.clear()
        self._keyed.clear()
        self.queued_bytes = 0
