"""The topics a run appears on in ROS 2 and Foxglove tools, and what is sent on them.

Per robot of a run (`<run>` and `<robot>` made valid ROS name tokens by `ros_token`): the
observed map, the ensemble mean and variance (nav_msgs/msg/OccupancyGrid), the pose
(geometry_msgs/msg/PoseStamped, heading the way the robot last moved), the plan and the
trajectory (nav_msgs/msg/Path), the LiDAR scan (sensor_msgs/msg/LaserScan), the frontiers
and the goal (visualization_msgs/msg/MarkerArray); for every run `/clock` (simulated time)
and the transforms `/tf` and `/tf_static` (map -> <run>/<robot>/odom -> <run>/<robot>/base_link
-> <run>/<robot>/base_scan). QoS per topic in `ROBOT_TOPICS` and `GRAPH_TOPICS`; the table
is in docs/interop.md#topics-mapexinteroptopics. `RunTopics` turns a run's arrays into
`Outgoing` messages; the bridges only send them.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from mapex.interop import foxglove_messages as fox
from mapex.interop import ros_messages as ros
from mapex.interop.ros_messages import MAP_FRAME, MapFrame


class TopicSpec(NamedTuple):
    """A topic's ROS type and QoS: latched (transient local, as maps: a late subscriber
    gets the last `depth` messages) or volatile; `depth` None: the bridge's own
    (`Ros2Config.latched_depth` / `volatile_depth`); best effort when not `reliable`."""

    ros_type: str
    latched: bool
    depth: int | None = None
    reliable: bool = True


CDR_ENCODING, ROS2MSG_ENCODING = "cdr", "ros2msg"  # ROS 2 messages and their schemas
TOPIC_ROOT = "mapex"
FOXGLOVE_ROOT = "foxglove"
# name -> (ROS type, latched[, depth, reliable]): per robot, /mapex/<run>/<robot>/<name>
ROBOT_TOPICS: dict[str, TopicSpec] = {
    "map": TopicSpec(ros.GRID_TYPE, True),
    "prediction_mean": TopicSpec(ros.GRID_TYPE, True),
    "prediction_variance": TopicSpec(ros.GRID_TYPE, True),
    "pose": TopicSpec(ros.POSE_TYPE, False),
    "plan": TopicSpec(ros.PATH_TYPE, True),
    "trajectory": TopicSpec(ros.PATH_TYPE, True),
    "scan": TopicSpec(ros.SCAN_TYPE, False),
    "frontiers": TopicSpec(ros.MARKERS_TYPE, False),
    "goal": TopicSpec(ros.MARKERS_TYPE, False),
}
CLOCK_TOPIC, TF_TOPIC, TF_STATIC_TOPIC = "/clock", "/tf", "/tf_static"
# one per ROS graph, with the QoS ROS gives them
GRAPH_TOPICS: dict[str, TopicSpec] = {
    CLOCK_TOPIC: TopicSpec(ros.CLOCK_TYPE, False, 1, reliable=False),  # rclcpp::ClockQoS
    TF_TOPIC: TopicSpec(ros.TF_TYPE, False, 100),  # tf2_ros::DynamicBroadcasterQoS
    TF_STATIC_TOPIC: TopicSpec(ros.TF_TYPE, True, 1),  # tf2_ros::StaticBroadcasterQoS
}
ODOM_FRAME, BASE_FRAME, SCAN_FRAME = "odom", "base_link", "base_scan"  # per robot (REP 105)
ROBOT_FRAMES = (ODOM_FRAME, BASE_FRAME, SCAN_FRAME)
KEPT_HEADINGS = 16  # steps whose heading a robot remembers (its pose and scan come apart)


def ros_token(text: str) -> str:
    """`text` as one valid ROS 2 name token: letters, digits and single underscores, not
    starting with a digit ('50052748_plan1-mapex' -> 'n50052748_plan1_mapex')."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", text)
    token = re.sub(r"_+", "_", token).strip("_") or "unnamed"
    return f"n{token}" if token[0].isdigit() else token


def robot_namespace(run: str, robot: str) -> str:
    """A robot's namespace, `<run>/<robot>` as ROS tokens: its topics are under
    /mapex/<namespace>/ and its frames are <namespace>/odom, /base_link and /base_scan."""
    return f"{ros_token(run)}/{ros_token(robot)}"


def robot_topic(run: str, robot: str, name: str) -> str:
    """The ROS 2 topic of one of a robot's `ROBOT_TOPICS`."""
    if name not in ROBOT_TOPICS:
        raise ValueError(f"unknown topic {name!r} (choose from {', '.join(ROBOT_TOPICS)})")
    return f"/{TOPIC_ROOT}/{robot_namespace(run, robot)}/{name}"


def robot_frame(run: str, robot: str, name: str) -> str:
    """The TF frame `name` (odom, base_link or base_scan) of a robot."""
    return f"{robot_namespace(run, robot)}/{name}"


def foxglove_topic(ros_topic: str) -> str:
    """The Foxglove channel beside a ROS 2 topic."""
    return f"/{FOXGLOVE_ROOT}{ros_topic}"


@dataclass(frozen=True)
class Outgoing:
    """One message to send: its ROS topic and type, the rosbags message, the Foxglove
    message of the same content (None without the SDK), and whether it is latched."""

    topic: str
    ros_type: str
    message: Any
    foxglove: Any | None
    latched: bool
    stamp_ns: int  # simulated time (mapex.interop.sim_time): header stamp and MCAP log time
    depth: int | None = None  # None: the bridge's latched or volatile depth
    reliable: bool = True


@dataclass(frozen=True)
class ChannelMessage:
    """One encoded message on one channel of a recording or a Foxglove server: the ROS
    topic's CDR (schema: the .msg text, encoding ros2msg) or the Foxglove topic's protobuf.
    `schema` gives (name, encoding, data); it is called only when the channel is new."""

    topic: str
    message_encoding: str
    schema: Callable[[], tuple[str, str, bytes]]
    data: bytes
    outgoing: Outgoing

    @property
    def is_ros(self) -> bool:
        return self.message_encoding == CDR_ENCODING


def channel_messages(outgoing: Outgoing) -> list[ChannelMessage]:
    """`outgoing` as its ROS channel's message and, with a Foxglove message, its Foxglove
    channel's (the one encoding the MCAP recording and the Foxglove server share)."""
    ros_type = outgoing.ros_type
    messages = [
        ChannelMessage(
            outgoing.topic, CDR_ENCODING,
            lambda: (ros_type, ROS2MSG_ENCODING, ros.message_definition(ros_type).encode()),
            ros.serialize(outgoing.message), outgoing,
        )
    ]  # fmt: skip
    if outgoing.foxglove is not None:
        foxglove = outgoing.foxglove

        def foxglove_schema() -> tuple[str, str, bytes]:
            schema = foxglove.get_schema()
            return schema.name, schema.encoding, bytes(schema.data)

        messages.append(
            ChannelMessage(
                foxglove_topic(outgoing.topic), fox.FOXGLOVE_ENCODING, foxglove_schema,
                foxglove.encode(), outgoing,
            )
        )  # fmt: skip
    return messages


def clock(stamp_ns: int) -> Outgoing:
    """The `/clock` message of simulated time `stamp_ns`."""
    return _graph_out(CLOCK_TOPIC, ros.clock(stamp_ns), stamp_ns)


@dataclass
class StaticFrames:
    """Every robot's static transforms, map -> <ns>/odom and <ns>/base_link ->
    <ns>/base_scan (both identity), sent whole on each change as tf2's static broadcaster
    does: /tf_static keeps one message for late subscribers, so it must hold them all."""

    transforms: dict[str, list[Any]] = field(default_factory=dict)  # namespace -> its two

    def add(self, run: str, robot: str, stamp_ns: int) -> list[Outgoing]:
        """The /tf_static message with this robot's frames, when they are new."""
        namespace = robot_namespace(run, robot)
        if namespace in self.transforms:
            return []
        odom, base, scan = (robot_frame(run, robot, n) for n in ROBOT_FRAMES)
        self.transforms[namespace] = [
            ros.transform(MAP_FRAME, odom, (0.0, 0.0), 0.0, stamp_ns),
            ros.transform(base, scan, (0.0, 0.0), 0.0, stamp_ns),
        ]
        return [self.message(stamp_ns)]

    def remove_run(self, run: str, stamp_ns: int) -> list[Outgoing]:
        """The /tf_static message without the frames of `run`, when it had some."""
        prefix = f"{ros_token(run)}/"
        gone = [namespace for namespace in self.transforms if namespace.startswith(prefix)]
        for namespace in gone:
            del self.transforms[namespace]
        return [self.message(stamp_ns)] if gone else []

    def message(self, stamp_ns: int) -> Outgoing:
        every = [t for transforms in self.transforms.values() for t in transforms]
        return _graph_out(TF_STATIC_TOPIC, ros.tf_message(every), stamp_ns)


@dataclass
class Heading:
    """A robot's heading: the direction of its last move (0 before any), kept when it
    stands still. Its pose and its scan of one step arrive apart (Zenoh orders samples per
    key only), so the heading of each of the last `KEPT_HEADINGS` steps is remembered and
    the first of the two to arrive moves it on; both arrive step by step, so steps are
    first heard in order."""

    cell: tuple[int, int] | None = None
    yaw_rad: float = 0.0
    stamp_ns: int = -1
    by_stamp: OrderedDict[int, float] = field(default_factory=OrderedDict)

    def at(self, cell: tuple[int, int], stamp_ns: int) -> float:
        """The heading (rad) at the step of `stamp_ns`, where the robot is at `cell`."""
        if stamp_ns in self.by_stamp:
            return self.by_stamp[stamp_ns]
        if stamp_ns < self.stamp_ns:  # older than the steps remembered
            return self.yaw_rad
        if self.cell is not None and cell != self.cell:
            self.yaw_rad = ros.heading_rad(self.cell, cell)
        self.cell, self.stamp_ns = cell, stamp_ns
        self.by_stamp[stamp_ns] = self.yaw_rad
        while len(self.by_stamp) > KEPT_HEADINGS:
            self.by_stamp.popitem(last=False)
        return self.yaw_rad


@dataclass
class RunTopics:
    """One run's messages: the map frame, every robot's trajectory and heading so far, and
    the static transforms (`statics`, shared by every run of one bridge)."""

    run: str
    frame: MapFrame
    with_foxglove: bool = True
    trajectories: dict[str, list[tuple[int, int]]] = field(default_factory=dict)
    statics: StaticFrames = field(default_factory=StaticFrames)
    headings: dict[str, Heading] = field(default_factory=dict)

    def observed(self, robot: str, codes: np.ndarray, stamp_ns: int) -> list[Outgoing]:
        """The observed map (uint8 codes of mapex.grid)."""
        message = ros.occupancy_grid(ros.observed_values(codes), self.frame, stamp_ns)
        foxglove = self._fox(fox.observed_grid, codes, stamp_ns)
        return [self._out(robot, "map", message, foxglove, stamp_ns)]

    def mean(self, robot: str, probability: np.ndarray, stamp_ns: int) -> list[Outgoing]:
        """The ensemble mean (occupancy probabilities in [0, 1])."""
        message = ros.occupancy_grid(ros.probability_values(probability), self.frame, stamp_ns)
        foxglove = self._fox(fox.probability_grid, probability, stamp_ns)
        return [self._out(robot, "prediction_mean", message, foxglove, stamp_ns)]

    def variance(self, robot: str, variance: np.ndarray, stamp_ns: int) -> list[Outgoing]:
        """The ensemble variance (0 .. 0.25), as 0..100 of 0.25 (`ros.variance_values`)."""
        values = ros.variance_values(variance)
        message = ros.occupancy_grid(values, self.frame, stamp_ns)
        scaled = values.astype(np.float64) / ros.OCCUPANCY_SCALE
        foxglove = self._fox(fox.probability_grid, scaled, stamp_ns)
        return [self._out(robot, "prediction_variance", message, foxglove, stamp_ns)]

    def heading(self, robot: str, cell: tuple[int, int], stamp_ns: int) -> float:
        """The robot's heading (rad) at the step of `stamp_ns`, where it is at `cell`."""
        return self.headings.setdefault(robot, Heading()).at(_cell(cell), stamp_ns)

    def pose(
        self, robot: str, cell: tuple[int, int], stamp_ns: int, with_trajectory: bool = True
    ) -> list[Outgoing]:
        """The pose, and the trajectory with it when the robot moved (and `with_trajectory`:
        a recording sends the whole path only now and then, its size grows with the run)."""
        cell = _cell(cell)
        yaw_rad = self.heading(robot, cell, stamp_ns)
        out = [
            self._out(
                robot, "pose", ros.pose_stamped(np.asarray(cell), self.frame, stamp_ns, yaw_rad),
                self._fox(fox.pose_in_frame, np.asarray(cell), stamp_ns), stamp_ns,
            )
        ]  # fmt: skip
        trajectory = self.trajectories.setdefault(robot, [])
        moved = not trajectory or trajectory[-1] != cell
        if moved:
            trajectory.append(cell)
        if moved and with_trajectory:
            out.append(self.trajectory(robot, stamp_ns))
        return out

    def transforms(self, robot: str, cell: tuple[int, int], stamp_ns: int) -> list[Outgoing]:
        """The robot's <ns>/odom -> <ns>/base_link transform on /tf (at its cell's centre,
        turned by its heading), after the whole /tf_static when the robot is new."""
        cell = _cell(cell)
        out = self.statics.add(self.run, robot, stamp_ns)
        xy_m = self.frame.cell_xy_m(np.asarray(cell))[0]
        message = ros.tf_message([
            ros.transform(
                robot_frame(self.run, robot, ODOM_FRAME), robot_frame(self.run, robot, BASE_FRAME),
                (xy_m[0], xy_m[1]), self.heading(robot, cell, stamp_ns), stamp_ns,
            )
        ])  # fmt: skip
        return [*out, _graph_out(TF_TOPIC, message, stamp_ns)]

    def scan(
        self,
        robot: str,
        cell: tuple[int, int],
        n_cells: np.ndarray,
        hit: np.ndarray,
        range_cells: int,
        stamp_ns: int,
        scan_time_s: float = 0.0,
    ) -> list[Outgoing]:
        """The LiDAR scan taken at `cell` (a `mapex.sensor.Scan`'s n_cells and hit), in the
        robot's base_scan frame."""
        cell = _cell(cell)
        message = ros.laser_scan(
            n_cells, hit, self.heading(robot, cell, stamp_ns), self.frame, range_cells,
            robot_frame(self.run, robot, SCAN_FRAME), stamp_ns, scan_time_s,
        )  # fmt: skip
        return [self._out(robot, "scan", message, None, stamp_ns)]

    def frontiers(
        self, robot: str, cells: np.ndarray, scores: np.ndarray, stamp_ns: int
    ) -> list[Outgoing]:
        """The frontier cells (int (k, 2)) as spheres coloured by score (float (k,))."""
        message = ros.frontier_markers(cells, scores, self.frame, stamp_ns)
        return [self._out(robot, "frontiers", message, None, stamp_ns)]

    def goal(self, robot: str, cell: tuple[int, int] | None, stamp_ns: int) -> list[Outgoing]:
        """The goal cell as a sphere (None: no goal, the sphere is deleted)."""
        goal = None if cell is None else _cell(cell)
        message = ros.goal_markers(goal, self.frame, stamp_ns)
        return [self._out(robot, "goal", message, None, stamp_ns)]

    def trajectory(self, robot: str, stamp_ns: int) -> Outgoing:
        """Every pose of the robot so far, as a path."""
        return self._path(robot, "trajectory", np.asarray(self.trajectories[robot]), stamp_ns)

    def plan(self, robot: str, cells: np.ndarray, stamp_ns: int) -> list[Outgoing]:
        """The planned path (int (k, 2) cells; empty: no goal)."""
        return [self._path(robot, "plan", np.asarray(cells).reshape(-1, 2), stamp_ns)]

    def _path(self, robot: str, name: str, cells: np.ndarray, stamp_ns: int) -> Outgoing:
        message = ros.path(cells, self.frame, stamp_ns)
        foxglove = self._fox(fox.poses_in_frame, cells, stamp_ns)
        return self._out(robot, name, message, foxglove, stamp_ns)

    def _fox(self, build, values, stamp_ns: int) -> Any | None:
        return build(values, self.frame, stamp_ns) if self.with_foxglove else None

    def _out(self, robot: str, name: str, message: Any, foxglove: Any, stamp_ns: int) -> Outgoing:
        spec = ROBOT_TOPICS[name]
        topic = robot_topic(self.run, robot, name)
        return Outgoing(
            topic, spec.ros_type, message, foxglove, spec.latched, stamp_ns, spec.depth,
            spec.reliable,
        )  # fmt: skip


def _graph_out(topic: str, message: Any, stamp_ns: int) -> Outgoing:
    spec = GRAPH_TOPICS[topic]
    return Outgoing(
        topic, spec.ros_type, message, None, spec.latched, stamp_ns, spec.depth, spec.reliable
    )


def _cell(cell: tuple[int, int] | np.ndarray) -> tuple[int, int]:
    return int(cell[0]), int(cell[1])
