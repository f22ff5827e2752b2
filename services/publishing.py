"""What the planner tells outside tools: its maps, frontiers, goal, path, metrics and status.

`RunPublisher` turns the episode's state after a step into messages on the robot's keys.
Encoding a whole map costs milliseconds, so messages are handed to a background thread
that keeps only the newest message per key and sends at most one batch per
`ServicesConfig.publish_period_s` (a viewer never slows the episode; it may skip frames,
never gets a stale one). `flush` waits until everything handed
over is out, e.g. the final status before the process exits. A late joiner `get`s the
latest message of every key (`LatestPublisher`).
"""

from __future__ import annotations

import logging
import threading

import numpy as np
import zenoh

from mapex.episode import EpisodeResult
from mapex.explorer import Explorer
from mapex.recorder import MetricCurves, MetricRecorder
from services.codec import DEFAULT_SERVICES
from services.config import ServicesConfig
from services.keys import ROBOT_TOPICS, robot_key
from services.latest import LatestPublisher
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

WORLD_TOPICS = ("step", "pose", "scan")  # a robot's keys the world serves or publishes
PUBLISHED_TOPICS = tuple(topic for topic in ROBOT_TOPICS if topic not in WORLD_TOPICS)
MUST_ARRIVE_TOPICS = ("status", "metrics")  # small, and the last one is never replaced

log = logging.getLogger("services.publishing")


class RunPublisher:
    """Publishes one robot's view of a run on `mapex/@v1/<run>/<robot>/...`."""

    def __init__(
        self,
        session: zenoh.Session,
        run: str,
        robot: str,
        services: ServicesConfig = DEFAULT_SERVICES,
        with_pose: bool = False,
    ) -> None:
        """`with_pose`: also publish the robot's pose after each step, for a planner that
        simulates its world itself (no world process publishes it then)."""
        topics = PUBLISHED_TOPICS + (("pose",) if with_pose else ())
        self.with_pose = with_pose
        self.keys = {topic: robot_key(run, robot, topic) for topic in topics}
        self.latest = LatestPublisher(
            session,
            list(self.keys.values()),
            blocking_keys=[self.keys[topic] for topic in MUST_ARRIVE_TOPICS],
        )
        # topic -> messages to put: the newest only, or every one for MUST_ARRIVE_TOPICS
        self._pending: dict[str, list[Message | _Lazy]] = {}
        self._busy = False
        self._closed = False
        self._flushing = False
        self.period_s = services.publish_period_s
        self._changed = threading.Condition()
        self._frontiers_id: int | None = None
        self._samples_seen = 0
        self._thread = threading.Thread(target=self._send_loop, name="publish", daemon=True)
        self._thread.start()

    def status(self, t: int, state: str, detail: str = "") -> None:
        """The run's state (starting, running, finished, failed)."""
        self._hand_over("status", StatusMessage(t, state, detail))

    def step(self, t: int, explorer: Explorer, recorder: MetricRecorder) -> None:
        """Everything that changed by step `t`: the map always, the rest when it changed."""
        self._hand_over("observed_map", _Lazy(t, "observed", explorer.observed.copy()))
        if self.with_pose:
            self._hand_over("pose", PoseMessage(t, tuple(int(v) for v in explorer.pose)))
        self._publish_plan(t, explorer)
        self._publish_metrics(recorder.curves, degraded=bool(explorer.stats.degraded_steps))

    def _publish_plan(self, t: int, explorer: Explorer) -> None:
        if explorer.stats.replans and id(explorer.frontiers) != self._frontiers_id:
            self._frontiers_id = id(explorer.frontiers)
            scores = explorer.frontier_scores
            if scores is None or len(scores) != len(explorer.frontiers):
                scores = np.full(len(explorer.frontiers), np.nan)
            self._hand_over(
                "frontiers",
                FrontiersMessage(t, explorer.frontiers, np.asarray(scores, dtype=np.float64)),
            )
            goal = None if explorer.goal is None else tuple(int(v) for v in explorer.goal)
            self._hand_over("goal", GoalMessage(t, goal))
            prediction = explorer.prediction
            if prediction is not None and len(prediction.answered):
                # P_t only when G was asked and answered (a method may read the members only)
                kinds = ("main",) if prediction.answered[0] == 0 else ()
                for kind in (*kinds, "mean", "variance"):
                    values = np.clip(getattr(prediction, kind), 0.0, 1.0)
                    self._hand_over(f"prediction/{kind}", _Lazy(t, kind, values))
        path = explorer.path if explorer.path is not None else np.zeros((0, 2), dtype=np.int64)
        self._hand_over("path", PathMessage(t, path.copy()))

    def finished(self, result: EpisodeResult, detail: str) -> None:
        """The last metric sample (taken after the last step) and the final status."""
        self._publish_metrics(result.curves, degraded=bool(result.stats.degraded_steps))
        self.status(result.steps, "finished", detail)

    def _publish_metrics(self, curves: MetricCurves, degraded: bool) -> None:
        """Every metric sample not published yet, in order (a curve has no gaps)."""
        for k in range(self._samples_seen, len(curves.steps)):
            tu = curves.tu[k]
            self._hand_over(
                "metrics",
                MetricsMessage(
                    curves.steps[k],
                    curves.coverage[k],
                    curves.iou[k],
                    None if not np.isfinite(tu) else tu,
                    degraded,
                ),
            )
        self._samples_seen = len(curves.steps)

    def flush(self, timeout_s: float = 5.0) -> None:
        """Wait until every message handed over so far has been put."""
        with self._changed:
            self._flushing = True
            self._changed.notify_all()
            self._changed.wait_for(lambda: not self._pending and not self._busy, timeout_s)
            self._flushing = False

    def close(self) -> None:
        """Flush, stop the sending thread and undeclare the keys."""
        self.flush()
        with self._changed:
            self._closed = True
            self._changed.notify_all()
        self._thread.join()
        self.latest.close()

    def _hand_over(self, topic: str, message: Message | _Lazy) -> None:
        """Queue `message`: it replaces a pending one of its topic, unless the topic must
        arrive (every status and metric sample is put, in order)."""
        with self._changed:
            if topic in MUST_ARRIVE_TOPICS:
                self._pending.setdefault(topic, []).append(message)
            else:
                self._pending[topic] = [message]
            self._changed.notify_all()

    def _send_loop(self) -> None:
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._pending or self._closed)
                if not self._pending:
                    return
                batch, self._pending = self._pending, {}
                self._busy = True
            for topic, messages in batch.items():
                for message in messages:
                    try:
                        ready = message.build() if isinstance(message, _Lazy) else message
                        self.latest.put(self.keys[topic], ready)
                    except (zenoh.ZError, ValueError) as error:
                        log.warning("could not publish %s: %s", topic, error)
            with self._changed:
                self._busy = False
                self._changed.notify_all()
                # at most one batch per period: newer messages replace older ones meanwhile
                self._changed.wait_for(lambda: self._closed or self._flushing, self.period_s)


class _Lazy:
    """A map checked and quantised on the sending thread, not the episode's."""

    def __init__(self, t: int, kind: str, values: np.ndarray) -> None:
        self.t, self.kind, self.values = t, kind, values

    def build(self) -> MapMessage:
        if self.kind == "observed":
            return MapMessage(self.t, "observed", self.values)
        return MapMessage.from_probabilities(self.t, self.kind, self.values)
