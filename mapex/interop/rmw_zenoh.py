"""What ROS 2's Zenoh middleware (rmw_zenoh, Jazzy >= 0.2.4, Kilted, Rolling) expects on the
wire, as strings and bytes: data keys, liveliness tokens, QoS text and sample attachments.

Taken from ros2/rmw_zenoh's docs/design.md and rmw_zenoh_cpp/src/detail
(liveliness_utils.cpp, attachment_helpers.cpp, qos.cpp, simplified_xxhash3.cpp); each
format is spelled out in docs/interop.md#the-ros-2-bridge-servicesbridgesros2. Pure
functions, no Zenoh session; `services.ros2` declares and publishes with them.
"""

from __future__ import annotations

import struct

from mapex.interop.xxh3 import xxh3_128_digest

ADMIN_SPACE = "@ros2_lv"
SLASH_REPLACEMENT = "%"
GID_BYTES = 16
ATTACHMENT_BYTES = 8 + 8 + 1 + GID_BYTES
RELIABLE, BEST_EFFORT = 1, 2  # rmw/types.h enum values
TRANSIENT_LOCAL, VOLATILE, KEEP_LAST = 1, 2, 1
_DEFAULT_DEPTH = 42  # rmw_zenoh's default history depth (qos.cpp)


def dds_type_name(ros_type: str) -> str:
    """'nav_msgs/msg/OccupancyGrid' -> 'nav_msgs::msg::dds_::OccupancyGrid_'."""
    package, kind, name = _type_parts(ros_type)
    return f"{package}::{kind}::dds_::{name}_"


def data_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The Zenoh key rmw_zenoh publishes and subscribes a topic's samples on."""
    return f"{domain_id}/{_strip_slashes(topic)}/{dds_type_name(ros_type)}/{type_hash}"


def mangle(name: str) -> str:
    """A name inside one token field: every '/' becomes '%' ('' too: unset)."""
    return name.replace("/", SLASH_REPLACEMENT) or SLASH_REPLACEMENT


def node_token(domain_id: int, zid: str, node_id: int, node: str, namespace: str = "/") -> str:
    """The liveliness token of a node (`ros2 node list`)."""
    parts = [ADMIN_SPACE, str(domain_id), zid, str(node_id), str(node_id), "NN"]
    return "/".join([*parts, mangle("/"), mangle(namespace), mangle(node)])


def publisher_token(
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    node: str,
    topic: str,
    ros_type: str,
    type_hash: str,
    qos: str,
    namespace: str = "/",
) -> str:
    """The liveliness token of a publisher (`ros2 topic list`, `ros2 topic info -v`)."""
    parts = [ADMIN_SPACE, str(domain_id), zid, str(node_id), str(entity_id), "MP"]
    names = [mangle("/"), mangle(namespace), mangle(node), mangle(topic)]
    return "/".join([*parts, *names, dds_type_name(ros_type), type_hash, qos])


def qos_text(latched: bool, depth: int, reliable: bool = True) -> str:
    """The QoS field of a keep-last publisher (rmw_zenoh's qos_to_keyexpr, a field equal to
    the default left empty): transient local when `latched` (':1:,1:,:,:,,' for a depth of
    1), else volatile ('::,10:,:,:,,' for 10); best effort when not `reliable` ('2::,1:,:,:,,'
    for /clock's depth of 1)."""
    reliability = "" if reliable else str(BEST_EFFORT)
    durability = str(TRANSIENT_LOCAL) if latched else ""
    depth_text = "" if depth == _DEFAULT_DEPTH else str(depth)
    return f"{reliability}:{durability}:,{depth_text}:,:,:,,"


def attachment(sequence: int, source_time_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of one sample."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"a publisher gid has {GID_BYTES} bytes, got {len(gid)}")
    return struct.pack("<qqB", sequence, source_time_ns, GID_BYTES) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence, source time ns, gid) of an attachment (ValueError when malformed)."""
    if len(data) != ATTACHMENT_BYTES or data[16] != GID_BYTES:
        raise ValueError(f"an rmw_zenoh attachment has {ATTACHMENT_BYTES} bytes")
    sequence, stamp_ns = struct.unpack_from("<qq", data)
    return sequence, stamp_ns, bytes(data[17:])


def publisher_gid(token: str) -> bytes:
    """The 16-byte gid of a publisher, as rmw_zenoh_cpp makes it (liveliness_utils.cpp,
    `Entity::Entity`): XXH3-128 of the whole liveliness token, its low 64 bits then its high
    64 bits, each little-endian. `ros2 topic info -v` shows it; a subscriber tells
    publishers apart by it."""
    return xxh3_128_digest(token.encode())


def _type_parts(ros_type: str) -> tuple[str, str, str]:
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"a ROS type looks like 'pkg/msg/Name', got {ros_type!r}")
    return parts[0], parts[1], parts[2]


def _strip_slashes(topic: str) -> str:
    """rmw_zenoh's strip_slashes: one leading and one trailing '/' removed."""
    start = 1 if topic.startswith("/") else 0
    end = -1 if topic.endswith("/") and len(topic) > start else None
    return topic[start:end]
