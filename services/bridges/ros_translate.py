"""A run's updates (services.bridges.follow) as the messages of its ROS 2 and Foxglove topics.

The one translation `services.ros2` (live, over rmw_zenoh) and `services.record` (MCAP)
share: maps, poses and paths become `mapex.interop.topics.Outgoing` messages in the run's
`map` frame, placed by the run's world info (shape, resolution) or, until it arrives, by
the first map's shape and `Ros2Config.default_resolution_m`. Zenoh orders samples per key
only, so a pose, path or status may arrive before the run's first map or world info: the
newest of each per robot is held until the run has a frame, then sent.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable

from mapex.interop.ros_messages import MapFrame
from mapex.interop.topics import Outgoing, RunTopics, ros_token
from services.bridges.follow import FINAL_STATES, Update
from services.config import Ros2Config
from services.messages import MapMessage

log = logging.getLogger("services.ros_translate")


class RunTranslator:
    """A `RunFollower` sink: each update as the ROS (and Foxglove) messages of
    `mapex.interop.topics`, handed to `send`: a ROS node's publish (`services.ros2`) or an
    MCAP recording's write (`services.record`). Keeps the `max_runs` newest runs; `forget`
    is told the topic prefix of an older run that goes."""

    def __init__(
        self,
        send: Callable[[Outgoing], None],
        config: Ros2Config,
        forget: Callable[[str], None] | None = None,
        with_foxglove: bool = False,
    ) -> None:
        self.send, self.forget, self.config = send, forget, config
        self.with_foxglove = with_foxglove
        self.runs: OrderedDict[str, RunTopics] = OrderedDict()
        self._frames: dict[str, MapFrame] = {}
        self._trajectory_sent_s: dict[tuple[str, str], float] = {}
        # run -> (robot, topic) -> newest update that came before the run had a frame
        self._held: dict[str, dict[tuple[str | None, str], Update]] = {}

    def __call__(self, update: Update) -> None:
        if update.topic == "world_info":
            info = update.message
            self._frames[update.run] = MapFrame(*info.shape, info.resolution_m)
            if update.run in self.runs:
                self.runs[update.run].frame = self._frames[update.run]
            else:
                self._run(update.run, info.shape)
            self._send_held(update.run)
            return
        if not isinstance(update.message, MapMessage) and update.run not in self.runs:
            self._hold(update)
            return  # no map and no world info of this run yet: no frame to place it in
        for outgoing in self._messages(update):
            self.send(outgoing)
        self._send_held(update.run)

    def _hold(self, update: Update) -> None:
        self._held.setdefault(update.run, {})[(update.robot, update.topic)] = update
        while len(self._held) > self.config.max_runs:  # runs that never show a map
            self._held.pop(next(iter(self._held)))

    def _send_held(self, run: str) -> None:
        for update in self._held.pop(run, {}).values():
            for outgoing in self._messages(update):
                self.send(outgoing)

    def _messages(self, update: Update) -> list[Outgoing]:
        message, stamp_ns, robot = update.message, time.time_ns(), update.robot
        if isinstance(message, MapMessage):
            topics = self._run(update.run, message.map_u8.shape)
            if update.topic == "observed_map":
                return topics.observed(robot, message.map_u8, stamp_ns)
            if update.topic == "prediction/mean":
                return topics.mean(robot, message.probabilities(), stamp_ns)
            return []
        topics = self.runs[update.run]
        if update.topic == "pose":
            return topics.pose(robot, message.pose, stamp_ns, self._trajectory_due(update))
        if update.topic == "path":
            return topics.plan(robot, message.cells, stamp_ns)
        ended = update.topic == "status" and message.state in FINAL_STATES
        if ended and robot in topics.trajectories:
            return [topics.trajectory(robot, stamp_ns)]  # the whole trajectory, last
        return []

    def _trajectory_due(self, update: Update) -> bool:
        """Whether this pose also sends the trajectory: at most once per
        `trajectory_period_s` per robot (a whole path per step would cost time quadratic in
        the run's length), and once more when the robot's run ends."""
        key, now_s = (update.run, update.robot), time.monotonic()
        if now_s - self._trajectory_sent_s.get(key, -math.inf) < self.config.trajectory_period_s:
            return False
        self._trajectory_sent_s[key] = now_s
        return True

    def _run(self, run: str, shape: tuple[int, int]) -> RunTopics:
        if run not in self.runs:
            frame = self._frames.get(run) or MapFrame(*shape, self.config.default_resolution_m)
            self.runs[run] = RunTopics(run, frame, self.with_foxglove)
            while len(self.runs) > self.config.max_runs:
                old, _ = self.runs.popitem(last=False)
                if self.forget is not None:
                    self.forget(f"/mapex/{ros_token(old)}/")
                log.info("run %s withdrawn (more than %d runs)", old, self.config.max_runs)
        return self.runs[run]
