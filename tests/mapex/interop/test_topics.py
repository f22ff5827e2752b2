"""Topic names and messages of a run for ROS 2 and Foxglove tools (mapex.interop.topics)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")
pytest.importorskip("foxglove", reason="the foxglove extra is not installed")

import math  # noqa: E402

from mapex.interop import ros_messages as ros  # noqa: E402
from mapex.interop.ros_messages import MapFrame  # noqa: E402
from mapex.interop.topics import (  # noqa: E402
    GRAPH_TOPICS,
    ROBOT_TOPICS,
    Heading,
    RunTopics,
    StaticFrames,
    clock,
    foxglove_topic,
    robot_frame,
    robot_topic,
    ros_token,
)

VALID_TOKEN = r"^[A-Za-z_][A-Za-z0-9_]*$"


@pytest.mark.parametrize(
    ("text", "token"),
    [
        ("r0", "r0"),
        ("50052748_plan1-mapex-start0", "n50052748_plan1_mapex_start0"),
        ("a--b__c-", "a_b_c"),
        ("---", "unnamed"),
        ("Run.7", "Run_7"),
    ],
)
def test_run_and_robot_ids_become_valid_ros_tokens(text, token):
    assert ros_token(text) == token
    assert __import__("re").match(VALID_TOKEN, ros_token(text))


def test_topic_names():
    assert robot_topic("up-1", "r1", "map") == "/mapex/up_1/r1/map"
    assert foxglove_topic("/mapex/up_1/r1/map") == "/foxglove/mapex/up_1/r1/map"
    with pytest.raises(ValueError, match="unknown topic 'maps'"):
        robot_topic("up", "r0", "maps")


def test_maps_are_latched_and_the_trajectory_grows_only_when_the_robot_moves():
    topics = RunTopics("demo", MapFrame(4, 5))
    (grid,) = topics.observed("r0", np.ones((4, 5), np.uint8), 7)
    assert grid.latched and grid.topic == "/mapex/demo/r0/map" and grid.stamp_ns == 7
    assert len(grid.foxglove.encode()) > 4 * 5 * 4  # RGBA cells
    first = topics.pose("r0", (1, 1), 8)
    same = topics.pose("r0", (1, 1), 9)
    moved = topics.pose("r0", (1, 2), 10)
    assert [o.topic.rsplit("/", 1)[1] for o in first] == ["pose", "trajectory"]
    assert len(same) == 1 and not same[0].latched
    assert len(moved[1].message.poses) == 2 and moved[1].foxglove is not None


def test_without_foxglove_only_ros_messages_are_made():
    topics = RunTopics("demo", MapFrame(4, 5), with_foxglove=False)
    (plan,) = topics.plan("r0", np.zeros((0, 2), int), 1)
    assert plan.foxglove is None and plan.message.poses == []


def test_a_robot_s_topics_and_frames_share_its_namespace():
    assert robot_topic("up-1", "r1", "scan") == "/mapex/up_1/r1/scan"
    assert robot_frame("up-1", "r1", "base_link") == "up_1/r1/base_link"


def test_the_qos_of_each_topic():
    latched = {name for name, spec in ROBOT_TOPICS.items() if spec.latched}
    assert latched == {"map", "prediction_mean", "prediction_variance", "plan", "trajectory"}
    assert GRAPH_TOPICS["/clock"] == (ros.CLOCK_TYPE, False, 1, False)  # rclcpp ClockQoS
    assert GRAPH_TOPICS["/tf"] == (ros.TF_TYPE, False, 100, True)  # tf2 dynamic broadcaster
    assert GRAPH_TOPICS["/tf_static"] == (ros.TF_TYPE, True, 1, True)  # tf2 static broadcaster
    tick = clock(2_000_000_001)
    assert (tick.topic, tick.stamp_ns, tick.reliable, tick.depth) == (
        "/clock",
        2_000_000_001,
        False,
        1,
    )
    assert (tick.message.clock.sec, tick.message.clock.nanosec) == (2, 1)


def test_every_static_frame_goes_out_in_each_tf_static_message():
    statics = StaticFrames()
    (first,) = statics.add("a", "r0", 5)
    assert statics.add("a", "r0", 6) == []  # known: nothing new to send
    (second,) = statics.add("b", "r1", 7)
    assert first.latched and second.stamp_ns == 7
    links = {(t.header.frame_id, t.child_frame_id) for t in second.message.transforms}
    assert links == {
        ("map", "a/r0/odom"), ("a/r0/base_link", "a/r0/base_scan"),
        ("map", "b/r1/odom"), ("b/r1/base_link", "b/r1/base_scan"),
    }  # fmt: skip
    (third,) = statics.remove_run("a", 8)
    assert len(third.message.transforms) == 2 and statics.remove_run("a", 9) == []


def test_the_heading_of_a_step_is_the_same_whichever_of_pose_and_scan_comes_first():
    heading = Heading()
    assert heading.at((5, 5), 0) == 0.0  # before any move
    assert heading.at((5, 6), 1) == 0.0  # right
    assert heading.at((4, 6), 2) == pytest.approx(math.pi / 2)  # up: the scan of step 2
    assert heading.at((5, 6), 1) == 0.0  # the pose of step 1, late
    assert heading.at((4, 6), 2) == pytest.approx(math.pi / 2)  # the pose of step 2
    assert heading.at((4, 6), 3) == pytest.approx(math.pi / 2)  # stood still: kept


def test_pose_transform_and_scan_of_a_step_agree():
    topics = RunTopics("demo", MapFrame(10, 10, 0.1))
    topics.pose("r0", (5, 5), 0)
    (pose,) = [o for o in topics.pose("r0", (4, 4), 1) if o.topic.endswith("/pose")]
    static, tf = topics.transforms("r0", (4, 4), 1)
    (scan,) = topics.scan("r0", (4, 4), np.array([2, 2], np.uint16), np.array([True, False]), 5, 1)
    assert (static.topic, tf.topic) == ("/tf_static", "/tf")
    yaw = 3 * math.pi / 4  # up and to the left
    assert 2 * math.atan2(
        pose.message.pose.orientation.z, pose.message.pose.orientation.w
    ) == pytest.approx(yaw)
    (link,) = tf.message.transforms
    assert 2 * math.atan2(link.transform.rotation.z, link.transform.rotation.w) == pytest.approx(
        yaw
    )
    assert (link.transform.translation.x, link.transform.translation.y) == pytest.approx(
        (0.45, 0.55)
    )
    assert scan.message.header.frame_id == "demo/r0/base_scan" and scan.foxglove is None
    assert scan.message.angle_min == pytest.approx(-yaw)  # ray 0 (along x) is at or after -pi
    variance = topics.variance("r0", np.full((10, 10), 0.25), 1)[0]
    assert variance.latched and variance.topic == "/mapex/demo/r0/prediction_variance"
