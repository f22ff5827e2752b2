"""Topic names and messages of a run for ROS 2 and Foxglove tools (mapex.interop.topics)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")
pytest.importorskip("foxglove", reason="the foxglove extra is not installed")

from mapex.interop.ros_messages import MapFrame  # noqa: E402
from mapex.interop.topics import RunTopics, foxglove_topic, robot_topic, ros_token  # noqa: E402

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
