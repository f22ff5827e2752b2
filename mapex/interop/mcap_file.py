"""MCAP recordings of a run (the `mcap` library's writer): a rosbag2 bag and, on request, a
Foxglove file beside it.

`RecordingProfile.ROS2` (`--record`) keeps the ROS 2 topics only, CDR with their `ros2msg`
schemas (the .msg text from `rosbags`), written as rosbag2_storage_mcap (Jazzy) writes a bag:
MCAP profile `ros2`, rosbag2's channel metadata (`offered_qos_profiles`, QoS YAML of bag
metadata version 9, and `topic_type_hash`) and, at close, the `rosbag2` metadata record
whose `serialized_metadata` is the bag's metadata YAML. rosbag2 plays a bag only when all
its topics share one serialization format, so the Foxglove channels (the same content as
protobuf `foxglove.Grid` / `PoseInFrame` / `PosesInFrame`, which Foxglove draws without a
ROS install) go to a file of their own: `RecordingProfile.FOXGLOVE` (`--record-foxglove`).
Needs the `ros` extra; what was checked against what: docs/interop.md#recording-mcap.
"""

from __future__ import annotations

import io
import os
import textwrap
from collections.abc import Iterable, Mapping
from contextlib import ExitStack
from enum import Enum
from pathlib import Path
from typing import Any

from mapex.interop.ros_messages import MissingExtraError, type_hash
from mapex.interop.topics import ChannelMessage, Outgoing, channel_messages

ROS_DISTRO = "jazzy"
# rosbag2_storage_mcap's bag-wide record and rosbag2_storage's BagMetadata (Jazzy)
ROSBAG2_RECORD = "rosbag2"
ROSBAG2_METADATA_VERSION = 9
STORAGE_IDENTIFIER = "mcap"
NO_MESSAGE_START_NS = 2**63 - 1  # a bag without messages starts at nanoseconds::max()
# offered QoS depth of a topic without its own, as the live bridge's Ros2Config defaults:
# latched topics keep their last message, the others 10
LATCHED_DEPTH, VOLATILE_DEPTH = 1, 10
YAML_LINE_WIDTH = 1 << 16  # long values (type hashes) stay on their key's line


class RecordingProfile(Enum):
    """Which channels a recording keeps: ROS 2 (CDR, a rosbag2 bag) or Foxglove (protobuf)."""

    ROS2 = "ros2"
    FOXGLOVE = "foxglove"

    @property
    def mcap_profile(self) -> str:
        """The MCAP header's profile: `ros2` (rosbag2 writes it, rosbags requires it); none
        for the Foxglove file."""
        return "ros2" if self is RecordingProfile.ROS2 else ""

    def keeps(self, message: ChannelMessage) -> bool:
        """Whether a file of this profile records `message` (CDR or protobuf)."""
        return message.is_ros == (self is RecordingProfile.ROS2)


def record_path_problem(path: Path) -> str | None:
    """Why `path` cannot take a new recording (it exists: recordings are never
    overwritten; or its directory does not exist), or None."""
    if path.exists():
        return f"{str(path)!r} exists (a recording is never overwritten)"
    if not path.parent.resolve().is_dir():
        return f"{str(path)!r}: directory {str(path.parent)!r} does not exist"
    return None


def recording_flags_problem(paths: Mapping[str, Path | None]) -> str | None:
    """The first problem of the recording flags (flag -> path, None where not given), one
    line naming the flag: a path `record_path_problem` refuses, or two flags naming one file."""
    given = {flag: Path(path) for flag, path in paths.items() if path is not None}
    for flag, path in given.items():
        if (problem := record_path_problem(path)) is not None:
            return f"{flag} {problem}"
    seen: dict[Path, str] = {}
    for flag, path in given.items():
        if (other := seen.setdefault(path.resolve(), flag)) != flag:
            return f"{other} and {flag} name the same file {str(path)!r}"
    return None


def offered_qos(
    latched: bool, depth: int | None = None, reliable: bool = True
) -> list[dict[str, Any]]:
    """rosbag2's `offered_qos_profiles` of a topic (metadata version 9 fields and names, by
    rosbags): keep last `depth`, reliable or best effort, transient local when `latched`
    else volatile, automatic liveliness, durations unspecified; `depth` None: 1 latched,
    10 volatile (what the live bridge offers)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2.metadata import dump_qos_v9

    unspecified = QosTime(0, 0)
    durability = QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE
    reliability = QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT
    if depth is None:
        depth = LATCHED_DEPTH if latched else VOLATILE_DEPTH
    qos = Qos(
        QosHistory.KEEP_LAST, depth, reliability, durability, unspecified, unspecified,
        QosLiveliness.AUTOMATIC, unspecified, False,
    )  # fmt: skip
    return [dict(profile) for profile in dump_qos_v9([qos])]


def rosbag2_yaml(data: Any) -> str:
    """`data` as YAML in the block style rosbag2's `YAML::Dump` (yaml-cpp) writes: keys in
    order, two-space indents, sequences indented under their key, no final newline (ruamel.yaml,
    the YAML library rosbags reads bags with; no anchors)."""
    from ruamel.yaml import YAML

    yaml = YAML(typ="safe", pure=True)
    yaml.default_flow_style = False
    yaml.representer.sort_base_mapping_type_on_output = False
    yaml.indent(mapping=2, sequence=4, offset=2)
    yaml.width = YAML_LINE_WIDTH
    yaml.representer.ignore_aliases = lambda _data: True  # a value written twice, twice
    stream = io.StringIO()
    yaml.dump(data, stream)
    return textwrap.dedent(stream.getvalue()).rstrip("\n")


class McapRecording:
    """An MCAP file being written with the channels of `profile`: `write` each `Outgoing`,
    then `close` (also on errors: the file is then a valid MCAP of what was written). Written
    under a hidden name and renamed on close, so a crash never leaves a file that looks
    finished."""

    def __init__(self, path: Path, profile: RecordingProfile = RecordingProfile.ROS2) -> None:
        try:
            from mcap.writer import Writer
        except ImportError as error:
            raise MissingExtraError(
                "MCAP recording needs the ros extra: pip install -e '.[ros]'"
            ) from error
        self.path, self.profile = Path(path), profile
        self._partial = self.path.with_name(f".{self.path.name}.partial")
        self._file = open(self._partial, "wb")  # noqa: SIM115 (closed in close())
        self._writer = Writer(self._file)
        self._writer.start(profile=profile.mcap_profile, library="mapex")
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[str, int] = {}
        self._topics: dict[int, dict[str, Any]] = {}  # channel -> rosbag2's topic_metadata
        self._counts: dict[int, int] = {}
        self._log_ns: tuple[int, int] | None = None  # earliest and latest log time
        self.messages = 0

    def write(self, outgoing: Outgoing) -> None:
        """Record one message on its channel of this profile (none: a Foxglove file is not
        given messages without a Foxglove form)."""
        self.write_messages(channel_messages(outgoing))

    def write_messages(self, messages: Iterable[ChannelMessage]) -> None:
        """Record the encoded messages of this profile, skip the others."""
        for message in messages:
            if self.profile.keeps(message):
                self._add(self._channel(message), message.data, message.outgoing.stamp_ns)

    def close(self) -> None:
        """Finish the file (rosbag2's metadata record, summary and indexes) and give it its
        name."""
        if self._file.closed:
            return
        if self.profile is RecordingProfile.ROS2:
            metadata = {"serialized_metadata": rosbag2_yaml(self.bag_metadata())}
            self._writer.add_metadata(ROSBAG2_RECORD, metadata)
        self._writer.finish()
        self._file.close()
        os.replace(self._partial, self.path)

    def discard(self) -> None:
        """Stop without a file (the hidden one is removed)."""
        if not self._file.closed:
            self._file.close()
        self._partial.unlink(missing_ok=True)

    def bag_metadata(self) -> dict[str, Any]:
        """rosbag2's BagMetadata of what was written, with the fields and order of its YAML
        encoding (rosbag2_storage/yaml.hpp, version 9), as rosbag2's writer fills them at
        close: times of the earliest and latest message, this one file."""
        start_ns, end_ns = self._log_ns or (NO_MESSAGE_START_NS, NO_MESSAGE_START_NS)
        starting_time = {"nanoseconds_since_epoch": start_ns}
        duration = {"nanoseconds": end_ns - start_ns}
        return {
            "version": ROSBAG2_METADATA_VERSION,
            "storage_identifier": STORAGE_IDENTIFIER,
            "duration": duration,
            "starting_time": starting_time,
            "message_count": self.messages,
            "topics_with_message_count": [
                {"topic_metadata": topic, "message_count": self._counts.get(channel, 0)}
                for channel, topic in self._topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [
                {
                    "path": self.path.name,
                    "starting_time": starting_time,
                    "duration": duration,
                    "message_count": self.messages,
                }
            ],  # fmt: skip
            "custom_data": None,
            "ros_distro": ROS_DISTRO,
        }

    def _add(self, channel: int, data: bytes, stamp_ns: int) -> None:
        sequence = self._counts.get(channel, 0)
        self._counts[channel] = sequence + 1
        self._writer.add_message(channel, stamp_ns, data, stamp_ns, sequence)
        first_ns, last_ns = self._log_ns or (stamp_ns, stamp_ns)
        self._log_ns = (min(first_ns, stamp_ns), max(last_ns, stamp_ns))
        self.messages += 1

    def _channel(self, message: ChannelMessage) -> int:
        """The channel of `message`'s topic, registered (with its schema) on first use; ROS
        channels carry rosbag2's metadata."""
        if message.topic not in self._channels:
            name, encoding, data = message.schema()
            if (name, encoding) not in self._schemas:
                self._schemas[name, encoding] = self._writer.register_schema(name, encoding, data)
            metadata, topic = {}, None
            if message.is_ros:
                outgoing = message.outgoing
                qos = offered_qos(outgoing.latched, outgoing.depth, outgoing.reliable)
                digest = type_hash(outgoing.ros_type)
                metadata = {"offered_qos_profiles": rosbag2_yaml(qos), "topic_type_hash": digest}
                topic = {
                    "name": message.topic, "type": outgoing.ros_type,
                    "serialization_format": message.message_encoding,
                    "offered_qos_profiles": qos, "type_description_hash": digest,
                }  # fmt: skip
            channel = self._writer.register_channel(
                message.topic, message.message_encoding, self._schemas[name, encoding], metadata
            )
            self._channels[message.topic] = channel
            if topic is not None:
                self._topics[channel] = topic
        return self._channels[message.topic]


class Recordings:
    """The recordings asked for, fed the same messages: the rosbag2 bag (`--record`) and/or
    the Foxglove file (`--record-foxglove`). A file that cannot be opened: the other one is
    discarded and the OSError raised."""

    def __init__(self, ros_path: Path | None = None, foxglove_path: Path | None = None) -> None:
        if ros_path is None and foxglove_path is None:
            raise ValueError("no recording asked for")
        self.files: list[McapRecording] = []
        asked = ((ros_path, RecordingProfile.ROS2), (foxglove_path, RecordingProfile.FOXGLOVE))
        try:
            for path, profile in asked:
                if path is not None:
                    self.files.append(McapRecording(path, profile))
        except BaseException:
            for recording in self.files:
                recording.discard()
            raise

    @property
    def with_foxglove(self) -> bool:
        """Whether a file wants the Foxglove form of the messages."""
        return any(f.profile is RecordingProfile.FOXGLOVE for f in self.files)

    def write(self, outgoing: Outgoing) -> None:
        """Record one message in every file (encoded once)."""
        messages = channel_messages(outgoing)
        for recording in self.files:
            recording.write_messages(messages)

    def close(self) -> str:
        """Finish every file (each one even when another fails); what was written."""
        with ExitStack() as stack:
            for recording in reversed(self.files):
                stack.callback(recording.close)
        return self.describe()

    def describe(self) -> str:
        """'N messages -> PATH' per file."""
        return ", ".join(f"{f.messages} messages -> {f.path}" for f in self.files)
