"""rmw_zenoh's wire strings and bytes (mapex.interop.rmw_zenoh), against ros2/rmw_zenoh's
design document examples and the published RIHS01 hashes."""

from __future__ import annotations

import struct

import pytest

from mapex.interop import rmw_zenoh as rmw

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
# RIHS01 hashes of the ROS 2 Jazzy packages (rosidl's generated EXPECTED_HASH constants)
PUBLISHED_HASHES = {
    "nav_msgs/msg/OccupancyGrid": (
        "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
    ),
    "geometry_msgs/msg/PoseStamped": (
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
    ),
    "nav_msgs/msg/Path": "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
}


def test_dds_type_names():
    assert rmw.dds_type_name("std_msgs/msg/String") == "std_msgs::msg::dds_::String_"
    assert rmw.dds_type_name("nav_msgs/msg/OccupancyGrid") == "nav_msgs::msg::dds_::OccupancyGrid_"
    with pytest.raises(ValueError, match="pkg/msg/Name"):
        rmw.dds_type_name("OccupancyGrid")


def test_the_data_key_is_the_design_documents():
    key = rmw.data_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH)
    assert key == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"


def test_node_and_publisher_tokens_are_the_design_documents_examples():
    zid = "8b20917502ee955ac4476e0266340d5c"
    assert rmw.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener") == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    )
    token = rmw.publisher_token(
        2, zid, 0, 10, "talker", "/chatter", "std_msgs/msg/String", STRING_HASH,
        rmw.qos_text(latched=False, depth=7),
    )  # fmt: skip
    assert token == (
        f"@ros2_lv/2/{zid}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,"
    )


def test_names_with_slashes_are_mangled():
    assert rmw.mangle("/mapex/run/r0/map") == "%mapex%run%r0%map"
    assert rmw.mangle("") == "%"


@pytest.mark.parametrize(
    ("latched", "depth", "text"),
    [(True, 1, ":1:,1:,:,:,,"), (False, 10, "::,10:,:,:,,"), (False, 42, "::,:,:,:,,")],
)
def test_qos_text(latched, depth, text):
    assert rmw.qos_text(latched, depth) == text
    assert text.count(":") == 5  # the six fields rmw_zenoh's parser needs


def test_the_attachment_is_33_little_endian_bytes():
    gid = bytes(range(16))
    data = rmw.attachment(3, 1_700_000_000_123_456_789, gid)
    assert len(data) == 33
    assert data[:8] == (3).to_bytes(8, "little")
    assert data[8:16] == struct.pack("<q", 1_700_000_000_123_456_789)
    assert data[16] == 0x10 and data[17:] == gid
    assert rmw.parse_attachment(data) == (3, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError, match="33 bytes"):
        rmw.parse_attachment(data[:-1])
    with pytest.raises(ValueError, match="16 bytes"):
        rmw.attachment(1, 0, b"short")


def test_the_attachment_matches_zenohs_own_serialiser():
    ext = pytest.importorskip("zenoh.ext")
    gid = rmw.publisher_gid("@ros2_lv/0/x/0/1/MP/%/%/n/%t/t/h/q")
    expected = ext.z_serialize((ext.Int64(5), ext.Int64(123), gid)).to_bytes()
    assert rmw.attachment(5, 123, gid) == expected


def test_gids_are_stable_and_differ_between_publishers():
    assert rmw.publisher_gid("a") == rmw.publisher_gid("a") != rmw.publisher_gid("b")
    assert len(rmw.publisher_gid("a")) == 16


@pytest.mark.parametrize("ros_type", sorted(PUBLISHED_HASHES))
def test_rosbags_recomputes_the_published_type_hashes(ros_type):
    pytest.importorskip("rosbags", reason="the ros extra is not installed")
    from mapex.interop.ros_messages import type_hash

    assert type_hash(ros_type) == PUBLISHED_HASHES[ros_type]
