"""ROS 2 messages of a run (mapex.interop.ros_messages): values, frame, CDR and hashes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")

from mapex.grid import FREE, OCCUPIED, UNKNOWN  # noqa: E402
from mapex.interop import ros_messages as ros  # noqa: E402
from mapex.interop.ros_messages import MapFrame  # noqa: E402

# RIHS01 hashes as ROS 2 Jazzy publishes them (rmw_zenoh puts them in every key)
KNOWN_HASHES = {
    ros.GRID_TYPE: "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
}


def _codes() -> np.ndarray:
    codes = np.full((6, 9), UNKNOWN, dtype=np.uint8)
    codes[1:4, 1:7] = FREE
    codes[0, :] = OCCUPIED
    return codes


def test_the_occupancy_grid_type_hash_is_the_published_constant():
    for ros_type, expected in KNOWN_HASHES.items():
        assert ros.type_hash(ros_type) == expected


@pytest.mark.parametrize("ros_type", ros.ROS_TYPES)
def test_every_type_has_a_hash_and_a_definition(ros_type):
    assert ros.type_hash(ros_type).startswith("RIHS01_") and len(ros.type_hash(ros_type)) == 71
    assert ros.message_definition(ros_type).splitlines()[0].startswith(("std_msgs/Header",))


def test_observed_values_are_minus_one_zero_hundred():
    values = ros.observed_values(_codes())
    assert values.dtype == np.int8
    assert values[0, 0] == 100 and values[2, 2] == 0 and values[5, 8] == -1


def test_a_grid_round_trips_through_cdr_cell_for_cell_with_row_zero_at_the_top():
    frame = MapFrame(6, 9, 0.1)
    message = ros.occupancy_grid(ros.observed_values(_codes()), frame, 1_500_000_000)
    back = ros.deserialize(ros.serialize(message), ros.GRID_TYPE)
    assert (
        back.info.width == 9
        and back.info.height == 6
        and back.info.resolution == pytest.approx(0.1)
    )
    assert back.header.frame_id == "map" and back.header.stamp.sec == 1
    assert back.header.stamp.nanosec == 500_000_000
    assert np.array_equal(ros.grid_values_in_map_order(back), ros.observed_values(_codes()))
    assert list(back.data[-9:]) == [100] * 9  # our row 0 is the grid's last row (y up)


def test_probabilities_become_0_to_100():
    values = ros.probability_values(np.array([[0.0, 0.254, 1.0, 1.7]]))
    assert values.tolist() == [[0, 25, 100, 100]]


def test_cells_sit_at_their_centres_in_the_map_frame():
    frame = MapFrame(rows=10, cols=20, resolution_m=0.1)
    xy = frame.cell_xy_m(np.array([[9, 0], [0, 19]]))
    assert np.allclose(xy, [[0.05, 0.05], [1.95, 0.95]])
    pose = ros.pose_stamped(np.array([9, 0]), frame, 0)
    assert (pose.pose.position.x, pose.pose.position.y, pose.pose.orientation.w) == (
        pytest.approx(0.05), pytest.approx(0.05), 1.0,
    )  # fmt: skip
    path = ros.deserialize(
        ros.serialize(ros.path(np.array([[9, 0], [8, 0]]), frame, 0)), ros.PATH_TYPE
    )
    assert [round(p.pose.position.y, 2) for p in path.poses] == [0.05, 0.15]
