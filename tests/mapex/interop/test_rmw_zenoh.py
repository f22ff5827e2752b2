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
    ("latched", "depth", "reliable", "text"),
    [
        (True, 1, True, ":1:,1:,:,:,,"),
        (False, 10, True, "::,10:,:,:,,"),
        (False, 42, True, "::,:,:,:,,"),
        (False, 1, False, "2::,1:,:,:,,"),  # /clock: rclcpp::ClockQoS
        (False, 100, True, "::,100:,:,:,,"),  # /tf: tf2_ros::DynamicBroadcasterQoS
    ],
)
def test_qos_text(latched, depth, reliable, text):
    assert rmw.qos_text(latched, depth, reliable) == text
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


# XXH3-128 (seed 0) values of the reference implementation (Cyan4973/xxHash, the C library
# rmw_zenoh_cpp's simplified_xxhash3.cpp is cut from), as (low64, high64)
XXH3_128 = {
    b"": (0x6001C324468D497F, 0x99AA06D3014798D8),  # xxHash's published empty-input value
}
# gid = XXH3-128 of the whole token, low64 then high64 little-endian (rmw_zenoh_cpp
# liveliness_utils.cpp, Entity::Entity); values from the reference library
TOKEN_GIDS = {
    (
        f"@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    ): "ac170f31eadcd9ff0cd86d7a17907d1c",  # 184 bytes: the 129-240 branch
    (
        "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/3/MP/%/%/mapex_bridge/%mapex%"
        "a_very_long_run_name_for_the_long_branch_of_xxh3_0123456789%r0%prediction_variance/"
        "nav_msgs::msg::dds_::OccupancyGrid_/"
        "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7/:1:,1:,:,:,,"
    ): "6c78ce15d87b5a01adc05cccb9d4dd20",  # 278 bytes: the long-input loop
}


def test_the_gid_is_xxh3_128_of_the_token_as_rmw_zenoh_makes_it():
    from mapex.interop.xxh3 import xxh3_128

    for data, value in XXH3_128.items():
        assert xxh3_128(data) == value
    for token, gid in TOKEN_GIDS.items():
        assert rmw.publisher_gid(token).hex() == gid


# XXH3-128 of bytes (7 i + 3) % 256, i < length, by the reference library: every branch of
# the algorithm (1-3, 4-8, 9-16, 17-128, 129-240 bytes, and the long loop, one block and more)
XXH3_128_BY_LENGTH = {
    1: (0x13E608BC156DEFED, 0x22BBB76B211A39BA),
    3: (0xA9088DDA485B481C, 0xCE31763CBF8245A5),
    4: (0x788A609154B0FE20, 0x47197970590746B1),
    8: (0x3CD024E3D63A1588, 0xE3BC8A5F46171555),
    9: (0xEAFAB1C7F123109F, 0xC72C88247A9A56D7),
    16: (0x60D75C5E47D40A24, 0xCE0B9647AB24F884),
    17: (0xEEED7654312A26D7, 0xBFD327EDCC2FBD12),
    128: (0xC580008B6C92AC53, 0x1B1962A096BAC78B),
    129: (0xBD91CE7ACE4D385B, 0x293E4968C4619023),
    240: (0x04E0B5F034BEE80B, 0xAD46C1021B076BC7),
    241: (0x8BEADD3A8874FE17, 0xAC6C3492C3D6B45D),
    1024: (0x9B81661C641C72B1, 0x18BC0EACA9A33636),
    2049: (0x55AED42C9F1554B6, 0xFC9DA7340154DC6C),
}


@pytest.mark.parametrize("length", sorted(XXH3_128_BY_LENGTH))
def test_xxh3_128_matches_the_reference_library_at_every_branch(length):
    from mapex.interop.xxh3 import xxh3_128

    data = bytes((7 * i + 3) % 256 for i in range(length))
    assert xxh3_128(data) == XXH3_128_BY_LENGTH[length]


@pytest.mark.parametrize("ros_type", sorted(PUBLISHED_HASHES))
def test_rosbags_recomputes_the_published_type_hashes(ros_type):
    pytest.importorskip("rosbags", reason="the ros extra is not installed")
    from mapex.interop.ros_messages import type_hash

    assert type_hash(ros_type) == PUBLISHED_HASHES[ros_type]
