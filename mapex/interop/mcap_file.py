"""A rosbag2-compatible MCAP recording of a run (the `mcap` library's writer).

ROS 2 channels hold CDR messages with their `ros2msg` schema (the .msg text from
`rosbags`) and the metadata rosbag2 writes (`offered_qos_profiles`, `topic_type_hash`), so
`ros2 bag play run.mcap` replays them and Foxglove / Lichtblick decode them; beside each one
a Foxglove channel holds the same content as protobuf `foxglove.Grid` / `PoseInFrame` /
`PosesInFrame`, which Foxglove draws without a ROS install. Needs the `ros` extra.
"""

from __future__ import annotations

import os
from pathlib import Path

from mapex.interop.ros_messages import MissingExtraError, type_hash
from mapex.interop.topics import ChannelMessage, Outgoing, channel_messages

PROFILE = "ros2"
ROS_DISTRO = "jazzy"
# rosbag2's QoS YAML (Jazzy field names and enum values: reliability 1 reliable, durability
# 1 transient local / 2 volatile, history 1 keep last; durations 0 = unspecified)
_QOS_YAML = (
    "- history: 1\n  depth: {depth}\n  reliability: 1\n  durability: {durability}\n"
    "  deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n"
    "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
    "  avoid_ros_namespace_conventions: false\n"
)


def record_path_problem(path: Path) -> str | None:
    """Why `path` cannot take a new recording (it exists: recordings are never
    overwritten; or its directory does not exist), or None."""
    if path.exists():
        return f"{str(path)!r} exists (a recording is never overwritten)"
    if not path.parent.resolve().is_dir():
        return f"{str(path)!r}: directory {str(path.parent)!r} does not exist"
    return None


def offered_qos(latched: bool) -> str:
    """rosbag2's `offered_qos_profiles` of a topic: reliable, keep last; latched maps are
    transient local with depth 1, the rest volatile with depth 10."""
    return _QOS_YAML.format(depth=1 if latched else 10, durability=1 if latched else 2)


class McapRecording:
    """An MCAP file being written: `write` each `Outgoing`, then `close` (also on errors:
    the file is then a valid MCAP of what was written). Written under a hidden name and
    renamed on close, so a crash never leaves a file that looks finished."""

    def __init__(self, path: Path) -> None:
        try:
            from mcap.writer import Writer
        except ImportError as error:
            raise MissingExtraError(
                "MCAP recording needs the ros extra: pip install -e '.[ros]'"
            ) from error
        self.path = Path(path)
        self._partial = self.path.with_name(f".{self.path.name}.partial")
        self._file = open(self._partial, "wb")  # noqa: SIM115 (closed in close())
        self._writer = Writer(self._file)
        self._writer.start(profile=PROFILE, library="mapex")
        self._writer.add_metadata("rosbag2", {"ROS_DISTRO": ROS_DISTRO})
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.messages = 0

    def write(self, outgoing: Outgoing) -> None:
        """Record one message on its ROS channel and, if present, its Foxglove channel."""
        for message in channel_messages(outgoing):
            self._add(self._channel(message), message.data, outgoing.stamp_ns)

    def close(self) -> None:
        """Finish the file (summary and indexes) and give it its name."""
        if self._file.closed:
            return
        self._writer.finish()
        self._file.close()
        os.replace(self._partial, self.path)

    def _add(self, channel: int, data: bytes, stamp_ns: int) -> None:
        sequence = self._sequence.get(channel, 0)
        self._sequence[channel] = sequence + 1
        self._writer.add_message(channel, stamp_ns, data, stamp_ns, sequence)
        self.messages += 1

    def _channel(self, message: ChannelMessage) -> int:
        """The channel of `message`'s topic, registered (with its schema) on first use; ROS
        channels carry rosbag2's metadata."""
        if message.topic not in self._channels:
            name, encoding, data = message.schema()
            if (name, encoding) not in self._schemas:
                self._schemas[name, encoding] = self._writer.register_schema(name, encoding, data)
            metadata = {}
            if message.is_ros:
                metadata = {
                    "offered_qos_profiles": offered_qos(message.outgoing.latched),
                    "topic_type_hash": type_hash(message.outgoing.ros_type),
                }
            self._channels[message.topic] = self._writer.register_channel(
                message.topic, message.message_encoding, self._schemas[name, encoding], metadata
            )
        return self._channels[message.topic]
