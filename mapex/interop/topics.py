"""The topics a run appears on in ROS 2 and Foxglove tools, and what is sent on them.

Per robot of a run (`<run>` and `<robot>` made valid ROS name tokens by `ros_token`): the
observed map and the ensemble mean (nav_msgs/msg/OccupancyGrid, latched: transient local,
the last one kept for late subscribers), the pose (geometry_msgs/msg/PoseStamped), the plan
and the trajectory (nav_msgs/msg/Path), each also as a Foxglove schema; the table is in
docs/interop.md#topics-mapexinteroptopics. `RunTopics` turns a run's arrays into `Outgoing`
messages; the bridges only send them.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mapex.interop import foxglove_messages as fox
from mapex.interop import ros_messages as ros
from mapex.interop.ros_messages import MapFrame

CDR_ENCODING, ROS2MSG_ENCODING = "cdr", "ros2msg"  # ROS 2 messages and their schemas
TOPIC_ROOT = "mapex"
FOXGLOVE_ROOT = "foxglove"
# name -> (ROS type, latched)
ROBOT_TOPICS: dict[str, tuple[str, bool]] = {
    "map": (ros.GRID_TYPE, True),
    "prediction_mean": (ros.GRID_TYPE, True),
    "pose": (ros.POSE_TYPE, False),
    "plan": (ros.PATH_TYPE, False),
    "trajectory": (ros.PATH_TYPE, False),
}


def ros_token(text: str) -> str:
    """`text` as one valid ROS 2 name token: letters, digits and single underscores, not
    starting with a digit ('50052748_plan1-mapex' -> 'n50052748_plan1_mapex')."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", text)
    token = re.sub(r"_+", "_", token).strip("_") or "unnamed"
    return f"n{token}" if token[0].isdigit() else token


def robot_topic(run: str, robot: str, name: str) -> str:
    """The ROS 2 topic of one of a robot's `ROBOT_TOPICS`."""
    if name not in ROBOT_TOPICS:
        raise ValueError(f"unknown topic {name!r} (choose from {', '.join(ROBOT_TOPICS)})")
    return f"/{TOPIC_ROOT}/{ros_token(run)}/{ros_token(robot)}/{name}"


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
    stamp_ns: int


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


@dataclass
class RunTopics:
    """One run's messages: the map frame and every robot's trajectory so far."""

    run: str
    frame: MapFrame
    with_foxglove: bool = True
    trajectories: dict[str, list[tuple[int, int]]] = field(default_factory=dict)

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

    def pose(
        self, robot: str, cell: tuple[int, int], stamp_ns: int, with_trajectory: bool = True
    ) -> list[Outgoing]:
        """The pose, and the trajectory with it when the robot moved (and `with_trajectory`:
        a recording sends the whole path only now and then, its size grows with the run)."""
        cell = (int(cell[0]), int(cell[1]))
        out = [
            self._out(
                robot, "pose", ros.pose_stamped(np.asarray(cell), self.frame, stamp_ns),
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
        ros_type, latched = ROBOT_TOPICS[name]
        topic = robot_topic(self.run, robot, name)
        return Outgoing(topic, ros_type, message, foxglove, latched, stamp_ns)
