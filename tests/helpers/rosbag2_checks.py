"""What `ros2 bag play FILE.mcap` (ROS 2 Jazzy) needs of an MCAP file, reproduced from
rosbag2's source, since no ROS 2 can be installed here to run it.

`rosbag2_play_problems(path)` lists, one line each, every condition the file breaks, each
named by the rosbag2 file and function that checks it (ros2/rosbag2, branch jazzy):

* rosbag2_storage_mcap/src/mcap_storage.cpp: the writer's profile `ros2`
  (`McapWriterOptions`); `read_metadata`: the summary's Statistics record (`statistics()
  .value()`), a schema for every channel, the `rosbag2` metadata records found through
  the metadata index, `serialized_metadata` decoded as `convert<BagMetadata>::decode`
  does, each channel's `offered_qos_profiles` through `to_rclcpp_qos_vector` and its
  `topic_type_hash`; `message_indexes_present` (reading in receive-time order);
  `write_lock_free` (no negative log time); `update_metadata` (no message compression);
* rosbag2_cpp/src/rosbag2_cpp/readers/sequential_reader.cpp `open`: topics listed,
  `check_topics_serialization_formats` (one format), `check_converter_serialization_format`
  (cdr, rmw's format: no converter plugin needed);
* rosbag2_storage/include/rosbag2_storage/yaml.hpp (the metadata fields per version) and
  rosbag2_storage/src/rosbag2_storage/qos.cpp (`convert<rclcpp::QoS>::decode`: version 8
  integers or version 9 rmw names, as rmw/src/qos_string_conversions.c spells them);
* rosbag2_transport/src/rosbag2_transport/player.cpp: `publisher_qos_for_topic` and
  `create_generic_publisher(topic.name, topic.type, qos)`: a valid full topic name and a
  `pkg/msg/Type` of the Jazzy install;
* rosbag2_cpp/src/rosbag2_cpp/message_definitions/local_message_definition_source.cpp
  `get_full_text`: schema encoding `ros2msg`, the .msg text with every dependency in its own
  `MSG: ` section;
* rosbag2_cpp/src/rosbag2_cpp/writers/sequential_writer.cpp: what the writer puts in the
  metadata at close (counts, start and duration, file paths) matches the file.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from ruamel.yaml import YAML

ROSBAG2_VERSION = 9  # rosbag2_storage BagMetadata::version in Jazzy
RMW_SERIALIZATION_FORMAT = "cdr"  # rmw_get_serialization_format() of rmw_zenoh and the DDS rmws
# rmw/src/qos_string_conversions.c: the names `*_from_str` knows (others are UNKNOWN)
RMW_NAMES = {
    "history": {"system_default", "keep_last", "keep_all"},
    "reliability": {"system_default", "reliable", "best_effort"},
    "durability": {"system_default", "transient_local", "volatile"},
    "liveliness": {"system_default", "automatic", "manual_by_topic"},
}
# version 8 integers: the rmw enums without UNKNOWN (history 3, reliability 3,
# durability 3, liveliness 4) and the deprecated manual_by_node (liveliness 2)
RMW_INTEGERS = {
    "history": {0, 1, 2},
    "reliability": {0, 1, 2},
    "durability": {0, 1, 2},
    "liveliness": {0, 1, 3},
}
HISTORY_UNKNOWN = 3  # qos.cpp's auto-detection takes integers up to UNKNOWN as version 8
QOS_DURATIONS = ("deadline", "lifespan", "liveliness_lease_duration")
MSG_DELIMITER = "=" * 80 + "\n"
# local_message_definition_source.cpp's MSG_FIELD_TYPE_REGEX and PRIMITIVE_TYPES
MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
PRIMITIVE_TYPES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string",
}  # fmt: skip
ROS_TYPE = re.compile(r"^[a-zA-Z0-9_]+/msg/[a-zA-Z0-9_]+$")
TYPE_HASH = re.compile(r"^RIHS01_[0-9a-f]{64}$")
# rmw_validate_full_topic_name: '/'-separated tokens of letters, digits and '_', none
# starting with a digit; at most RMW_TOPIC_MAX_NAME_LENGTH (255 - 8 reserved for prefixes)
TOPIC_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
TOPIC_MAX_LENGTH = 255 - 8


def rosbag2_play_problems(path: Path) -> list[str]:
    """Every condition of rosbag2 (Jazzy) that `path` breaks, one line each; [] when
    `ros2 bag play` gets through opening it, reading its metadata, creating a publisher per
    topic and reading its messages in receive-time order."""
    problems: list[str] = []
    with open(path, "rb") as handle:
        reader = make_reader(handle)
        header, summary = reader.get_header(), reader.get_summary()
        if header.profile != "ros2":
            problems.append(f"mcap_storage.cpp McapWriterOptions: profile {header.profile!r}")
        if summary is None or summary.statistics is None:
            return [*problems, "mcap_storage.cpp read_metadata: no Statistics record"]
        records = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
        indexed = [i for i in summary.metadata_indexes if i.name == "rosbag2"]
        log_times = _log_times(reader)
    problems += _channel_problems(summary)
    problems += _sequential_reader_problems(summary)
    if not indexed or len(indexed) != len(records):
        problems.append("mcap_storage.cpp read_metadata: no indexed 'rosbag2' metadata record")
    for record in records:
        problems += _bag_metadata_problems(record.metadata, summary, path)
    if not any(c.message_index_length > 0 for c in summary.chunk_indexes):
        problems.append("mcap_storage.cpp message_indexes_present: no message index")
    problems += _message_problems(log_times, summary.statistics)
    return problems


def decode_qos(node: Any) -> dict[str, Any]:
    """One QoS profile as qos.cpp `convert<rclcpp::QoS>::decode` reads it (an integer history
    up to UNKNOWN: version 8 integers, else version 9 names): the policies by rmw name;
    ValueError where yaml-cpp would throw or rmw gives UNKNOWN."""
    version8 = isinstance(node["history"], int) and 0 <= node["history"] <= HISTORY_UNKNOWN
    profile: dict[str, Any] = {}
    for policy, names in RMW_NAMES.items():
        value = node[policy]
        if version8 != isinstance(value, int) or isinstance(value, bool):
            raise ValueError(f"{policy} {value!r} mixes versions 8 and 9")
        if value not in (RMW_INTEGERS[policy] if version8 else names):
            raise ValueError(f"{policy} {value!r} is UNKNOWN to rmw")
        profile[policy] = value
    if profile["history"] in (1, "keep_last"):
        profile["depth"] = _int(node["depth"], "depth")
    for name in QOS_DURATIONS:
        profile[name] = (_int(node[name]["sec"], name), _int(node[name]["nsec"], name))
    if not isinstance(node["avoid_ros_namespace_conventions"], bool):
        raise ValueError("avoid_ros_namespace_conventions is not a bool")
    return profile


def decode_qos_text(text: str) -> list[dict[str, Any]]:
    """`to_rclcpp_qos_vector`: the profiles of a channel's `offered_qos_profiles` text."""
    node = YAML(typ="safe").load(text) if text else []
    if not isinstance(node, list):
        raise ValueError("offered_qos_profiles is not a sequence")
    return [decode_qos(profile) for profile in node]


def schema_problems(name: str, encoding: str, text: str) -> list[str]:
    """A ROS schema as get_full_text writes it: `ros2msg`, the root .msg text, then every
    (transitive) dependency after a delimiter and `MSG: pkg/Type`."""
    where = f"local_message_definition_source.cpp get_full_text ({name})"
    if encoding != "ros2msg":
        return [f"{where}: schema encoding {encoding!r}"]
    root, *sections = text.split(MSG_DELIMITER)
    defined: dict[str, str] = {}
    for section in sections:
        first, _, body = section.partition("\n")
        if not first.startswith("MSG: "):
            return [f"{where}: a section without 'MSG: ': {first!r}"]
        defined[_short_type(first.removeprefix("MSG: "))] = body
    problems = []
    for context, body in [(name, root), *defined.items()]:
        package = context.split("/")[0]
        for field_type in MSG_FIELD_TYPE.findall(body):
            if field_type in PRIMITIVE_TYPES or field_type.startswith("string<"):
                continue
            full = field_type if "/" in field_type else f"{package}/{field_type}"
            if _short_type(full) not in defined:
                problems.append(f"{where}: dependency {full} has no MSG: section")
    return problems


def _short_type(ros_type: str) -> str:
    """'pkg/msg/Type' and 'pkg/Type' as 'pkg/Type'."""
    package, *_, name = ros_type.split("/")
    return f"{package}/{name}"


def _int(value: Any, name: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise ValueError(f"{name} {value!r} is not a non-negative integer")
    return value


def _channel_problems(summary) -> list[str]:
    from rosbags.typesys import Stores, get_typestore

    jazzy = get_typestore(Stores.ROS2_JAZZY)
    problems = []
    for channel in summary.channels.values():
        topic = channel.topic
        schema = summary.schemas.get(channel.schema_id)
        if schema is None:
            problems.append(f"mcap_storage.cpp read_metadata: no schema for topic {topic}")
            continue
        if (problem := _topic_name_problem(topic)) is not None:
            problems.append(f"player.cpp create_generic_publisher: {topic}: {problem}")
        if not ROS_TYPE.match(schema.name) or schema.name not in jazzy.types:
            problems.append(f"player.cpp create_generic_publisher: {topic}: type {schema.name}")
        problems += schema_problems(
            schema.name, schema.encoding, schema.data.decode(errors="replace")
        )
        try:
            decode_qos_text(channel.metadata.get("offered_qos_profiles", ""))
        except (ValueError, KeyError, TypeError) as error:
            problems.append(f"qos.cpp to_rclcpp_qos_vector: {topic}: {error!r}")
        digest = channel.metadata.get("topic_type_hash", "")
        if not TYPE_HASH.match(digest) or (
            schema.name in jazzy.types and digest != jazzy.hash_rihs01(schema.name)
        ):
            problems.append(f"mcap_storage.cpp read_metadata: {topic}: topic_type_hash {digest!r}")
    return problems


def _topic_name_problem(topic: str) -> str | None:
    if not topic.startswith("/") or topic.endswith("/") or len(topic) > TOPIC_MAX_LENGTH:
        return "not a full topic name"
    bad = [token for token in topic[1:].split("/") if not TOPIC_TOKEN.match(token)]
    return f"bad tokens {bad}" if bad else None


def _sequential_reader_problems(summary) -> list[str]:
    formats = {channel.message_encoding for channel in summary.channels.values()}
    if not formats:
        return ["sequential_reader.cpp open: No topics were listed in metadata"]
    if len(formats) > 1:
        return [
            "sequential_reader.cpp check_topics_serialization_formats: Topics with different "
            f"rmw serialization format have been found ({sorted(formats)})"
        ]
    if formats != {RMW_SERIALIZATION_FORMAT}:
        return [f"sequential_reader.cpp check_converter_serialization_format: {formats}"]
    return []


def _bag_metadata_problems(record: dict[str, str], summary, path: Path) -> list[str]:
    """`serialized_metadata` decoded as yaml.hpp `convert<BagMetadata>::decode` does, and
    equal to what rosbag2's writer would have put there for this file."""
    where = "mcap_storage.cpp read_metadata: serialized_metadata"
    if "serialized_metadata" not in record:
        return [f"{where}: missing (rosbag2 then reads the QoS as version 8)"]
    try:
        bag = YAML(typ="safe").load(record["serialized_metadata"])
        topics = _decode_bag_metadata(bag)
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        return [f"yaml.hpp convert<BagMetadata>::decode: {error!r}"]
    stats, problems = summary.statistics, []
    channels = {c.topic: c for c in summary.channels.values()}
    listed = {t["topic_metadata"]["name"]: t for t in topics}
    if set(listed) != set(channels):
        problems.append(f"{where}: topics {sorted(listed)} != channels {sorted(channels)}")
    for name, topic in listed.items():
        channel, metadata = channels.get(name), topic["topic_metadata"]
        if channel is None:
            continue
        recorded = (
            summary.schemas[channel.schema_id].name, channel.message_encoding,
            decode_qos_text(channel.metadata.get("offered_qos_profiles", "")),
            channel.metadata.get("topic_type_hash"),
            stats.channel_message_counts.get(channel.id, 0),
        )  # fmt: skip
        serialized = (
            metadata["type"], metadata["serialization_format"],
            [decode_qos(q) for q in metadata["offered_qos_profiles"]],
            metadata["type_description_hash"], topic["message_count"],
        )  # fmt: skip
        if recorded != serialized:
            problems.append(f"{where}: {name}: {serialized} != the channel's {recorded}")
    start = stats.message_start_time if stats.message_count else 2**63 - 1
    expected = {
        "storage_identifier": "mcap",
        "message_count": stats.message_count,
        "starting_time": {"nanoseconds_since_epoch": start},
        "duration": {"nanoseconds": stats.message_end_time - stats.message_start_time},
        "relative_file_paths": [path.name],
        "compression_mode": "",  # update_metadata: MCAP refuses message compression
    }
    for key, value in expected.items():
        if bag[key] != value:
            problems.append(f"sequential_writer.cpp close: {key} {bag[key]!r} != {value!r}")
    file_info = {k: v for k, v in bag["files"][0].items() if k != "path"}
    if len(bag["files"]) != 1 or file_info != {k: expected[k] for k in file_info}:
        problems.append(f"sequential_writer.cpp close: files {bag['files']!r}")
    return problems


def _decode_bag_metadata(bag: dict[str, Any]) -> list[dict[str, Any]]:
    """yaml.hpp's decode of BagMetadata: the fields each version has, of their types; the
    topics_with_message_count."""
    version = _int(bag["version"], "version")
    if version > ROSBAG2_VERSION:
        raise ValueError(f"version {version} is newer than Jazzy's {ROSBAG2_VERSION}")
    str(bag["storage_identifier"])
    _int(bag["duration"]["nanoseconds"], "duration")
    _int(bag["starting_time"]["nanoseconds_since_epoch"], "starting_time")
    _int(bag["message_count"], "message_count")
    if not all(isinstance(p, str) for p in bag["relative_file_paths"]):
        raise ValueError("relative_file_paths")
    if version >= 3 and not (
        isinstance(bag["compression_format"], str) and isinstance(bag["compression_mode"], str)
    ):
        raise ValueError("compression_format / compression_mode")
    for info in bag["files"] if version >= 5 else []:
        str(info["path"])
        _int(info["starting_time"]["nanoseconds_since_epoch"], "files starting_time")
        _int(info["duration"]["nanoseconds"], "files duration")
        _int(info["message_count"], "files message_count")
    if version >= 6 and not isinstance(bag["custom_data"], dict | None):
        raise ValueError("custom_data is not a map")
    if version >= 8 and not isinstance(bag["ros_distro"], str):
        raise ValueError("ros_distro is not a string")
    topics = bag["topics_with_message_count"]
    for topic in topics:
        metadata = topic["topic_metadata"]
        for key in ("name", "type", "serialization_format"):
            if not isinstance(metadata[key], str):
                raise ValueError(f"topic {key}")
        qos = metadata["offered_qos_profiles"]
        if version >= 9:  # a sequence of profiles; older: the channel's text
            [decode_qos(profile) for profile in qos]
        if version >= 7 and not isinstance(metadata["type_description_hash"], str):
            raise ValueError("type_description_hash")
        _int(topic["message_count"], "message_count")
    return topics


def _log_times(reader) -> list[int]:
    return [message.log_time for _, _, message in reader.iter_messages()]


def _message_problems(log_times: list[int], stats) -> list[str]:
    problems = []
    if any(t < 0 for t in log_times):
        problems.append("mcap_storage.cpp write_lock_free: Invalid message timestamp")
    if len(log_times) != stats.message_count:
        problems.append(f"statistics: {stats.message_count} messages, {len(log_times)} read")
    elif log_times and (min(log_times), max(log_times)) != (
        stats.message_start_time, stats.message_end_time,
    ):  # fmt: skip
        problems.append("statistics: message start / end times are not the messages'")
    return problems
