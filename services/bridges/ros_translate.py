"""A run's updates (services.bridges.follow) as the messages of its ROS 2 and Foxglove topics.

The one translation `services.ros2` (live, over rmw_zenoh) and `services.record` (MCAP)
share: maps, poses, scans, paths, frontiers and goals become `mapex.interop.topics.Outgoing`
messages in the run's `map` frame, placed by the run's world info (shape, resolution, the
sensor's range) or, until it arrives, by the first map's shape and
`Ros2Config.default_resolution_m`. Every message is stamped in simulated time
(`mapex.interop.sim_time`) of the step it carries, and `/clock` ticks when a newer step is
heard. Zenoh orders samples per key only, so a pose, path or status may arrive before the
run's first map or world info: the newest of each per robot is held until the run has a
frame, then sent.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable

from mapex.config import SensorConfig
from mapex.interop.ros_messages import MapFrame
from mapex.interop.sim_time import DEFAULT_SIM_CLOCK, SimClock
from mapex.interop.topics import Outgoing, RunTopics, StaticFrames, clock, ros_token
from services.bridges.follow import FINAL_STATES, FOLLOWED_TOPICS, Update
from services.config import Ros2Config
from services.messages import MapMessage, ScanReply

# what a RunTranslator's follower follows: every followed topic, the scans included
TRANSLATED_TOPICS: tuple[str, ...] = tuple(FOLLOWED_TOPICS)

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
        sim_clock: SimClock = DEFAULT_SIM_CLOCK,
    ) -> None:
        self.send, self.forget, self.config = send, forget, config
        self.with_foxglove, self.sim_clock = with_foxglove, sim_clock
        self.runs: OrderedDict[str, RunTopics] = OrderedDict()
        self.statics = StaticFrames()  # every run's static transforms: one /tf_static
        self.clock_ns = -1  # the newest simulated time sent on /clock
        self._frames: dict[str, MapFrame] = {}
        self._range_cells: dict[str, int] = {}
        self._newest_t: dict[tuple[str, str | None], int] = {}
        self._trajectory_sent_s: dict[tuple[str, str], float] = {}
        # run -> (robot, topic) -> newest update that came before the run had a frame
        self._held: dict[str, dict[tuple[str | None, str], Update]] = {}

    def __call__(self, update: Update) -> None:
        if update.topic == "world_info":
            info = update.message
            self._frames[update.run] = MapFrame(*info.shape, info.resolution_m)
            if info.range_cells is not None:
                self._range_cells[update.run] = info.range_cells
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
        """`/clock` when the update's step is newer than any heard, then its messages."""
        stamp_ns = self.sim_clock.stamp_ns(self._step(update))
        ticks = []
        if stamp_ns > self.clock_ns:
            self.clock_ns = stamp_ns
            ticks.append(clock(stamp_ns))
        return ticks + self._translate(update, stamp_ns)

    def _step(self, update: Update) -> int:
        """The step an update is about; a scan of an older world (without its step) is
        taken to be of the robot's newest step heard."""
        key = (update.run, update.robot)
        t = getattr(update.message, "t", None)
        if t is None:
            return self._newest_t.get(key, 0)
        self._newest_t[key] = max(t, self._newest_t.get(key, t))
        return t

    def _translate(self, update: Update, stamp_ns: int) -> list[Outgoing]:
        message, robot, topic = update.message, update.robot, update.topic
        if isinstance(message, MapMessage):
            topics = self._run(update.run, message.map_u8.shape)
            if topic == "observed_map":
                return topics.observed(robot, message.map_u8, stamp_ns)
            if topic == "prediction/mean":
                return topics.mean(robot, message.probabilities(), stamp_ns)
            if topic == "prediction/variance":
                return topics.variance(robot, message.probabilities(), stamp_ns)
            return []
        topics = self.runs[update.run]
        if topic == "pose":
            due = self._trajectory_due(update)
            return topics.pose(robot, message.pose, stamp_ns, due) + topics.transforms(
                robot, message.pose, stamp_ns
            )
        if isinstance(message, ScanReply):
            return topics.scan(
                robot, message.pose, message.n_cells, message.hit, self._range(update.run),
                stamp_ns, self.sim_clock.seconds_per_step,
            )  # fmt: skip
        if topic == "path":
            return topics.plan(robot, message.cells, stamp_ns)
        if topic == "frontiers":
            return topics.frontiers(robot, message.cells, message.scores, stamp_ns)
        if topic == "goal":
            return topics.goal(robot, message.goal, stamp_ns)
        ended = topic == "status" and message.state in FINAL_STATES
        if ended and robot in topics.trajectories:
            return [topics.trajectory(robot, stamp_ns)]  # the whole trajectory, last
        return []

    def _range(self, run: str) -> int:
        """The run's sensor range in cells (its world info's; the default until then)."""
        return self._range_cells.get(run, SensorConfig().range_cells)

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
            self.runs[run] = RunTopics(run, frame, self.with_foxglove, statics=self.statics)
            while len(self.runs) > self.config.max_runs:
                old, _ = self.runs.popitem(last=False)
                if self.forget is not None:
                    self.forget(f"/mapex/{ros_token(old)}/")
                for outgoing in self.statics.remove_run(old, max(self.clock_ns, 0)):
                    self.send(outgoing)  # /tf_static without the run's frames
                self._range_cells.pop(old, None)
                for key in [key for key in self._newest_t if key[0] == old]:
                    del self._newest_t[key]
                log.info("run %s withdrawn (more than %d runs)", old, self.config.max_runs)
        return self.runs[run]
