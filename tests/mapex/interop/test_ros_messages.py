"""ROS 2 messages of a run (mapex.interop.ros_messages): values, frame, CDR and hashes."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ros extra is not installed")

from mapex.grid import FREE, OCCUPIED, UNKNOWN  # noqa: E402
from mapex.interop import ros_messages as ros  # noqa: E402
from mapex.interop.ros_messages import MapFrame  # noqa: E402
from mapex.raycast import ray_directions, trace_ray  # noqa: E402

# RIHS01 hashes as ROS 2 Jazzy publishes them (rmw_zenoh puts them in every key)
KNOWN_HASHES = {
    ros.GRID_TYPE: "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    ros.CLOCK_TYPE: "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564",
    ros.TF_TYPE: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    ros.SCAN_TYPE: "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
    ros.MARKERS_TYPE: "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
}
FIRST_FIELDS = {  # the first line of each type's .msg definition
    ros.CLOCK_TYPE: "builtin_interfaces/Time clock",
    ros.TF_TYPE: "geometry_msgs/TransformStamped[] transforms",
    ros.MARKERS_TYPE: "visualization_msgs/Marker[] markers",
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
    first = FIRST_FIELDS.get(ros_type, "std_msgs/Header header")
    assert ros.message_definition(ros_type).splitlines()[0] == first


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


def test_variance_is_scaled_to_its_largest_value():
    values = ros.variance_values(np.array([[0.0, 0.0625, 0.125, 0.25, 0.3]]))
    assert values.tolist() == [[0, 25, 50, 100, 100]]


@pytest.mark.parametrize(
    ("move", "yaw"),
    [((0, 1), 0.0), ((-1, 0), math.pi / 2), ((0, -3), math.pi), ((2, 0), -math.pi / 2),
     ((-1, 1), math.pi / 4)],
)  # fmt: skip
def test_the_heading_of_a_move_is_counter_clockwise_from_x(move, yaw):
    assert ros.heading_rad((5, 5), (5 + move[0], 5 + move[1])) == pytest.approx(yaw)
    pose = ros.pose_stamped(np.array([5, 5]), MapFrame(10, 10), 0, yaw)
    assert 2 * math.atan2(pose.pose.orientation.z, pose.pose.orientation.w) == pytest.approx(yaw)


@pytest.mark.parametrize("n_rays", [4, 360, 2500])
def test_ray_entry_distances_lie_on_the_entered_cells_boundary(n_rays):
    """The m-th entry distance of ray k puts a point on the ray at the border of the m-th
    cell it walks (Chebyshev distance half a cell from its centre), before the next one."""
    range_cells = 12
    table = ros.ray_entry_cells(n_rays, range_cells)
    for k in range(0, n_rays, max(1, n_rays // 40)):
        d_row, d_col = ray_directions(n_rays)[k]
        cells = trace_ray(40, 40, 20, 20, d_row, d_col, float(range_cells))
        entries = table[k, : len(cells)]
        assert entries[0] == 0 and np.all(np.diff(entries) >= 0)  # a corner: two at once
        points = np.array([20, 20]) + entries[:, None] * np.array([d_row, d_col])
        off = np.abs(points - cells).max(axis=1)
        assert np.allclose(off[1:], 0.5) and entries[-1] <= range_cells


def test_a_laser_scan_goes_counter_clockwise_from_minus_pi_of_the_heading():
    """Ray k of mapex.sensor points at -2 pi k / n in the map frame; the scan's angles are
    relative to the heading and start at or after -pi; a hit's range is the wall's face,
    a miss is +inf; range_max is the sensor's."""
    frame = MapFrame(30, 30, 0.1)
    n_cells = np.array([3, 4, 5, 6], np.uint16)  # rays right, down, left, up
    hit = np.array([True, False, True, True])
    scan = ros.laser_scan(n_cells, hit, 0.3, frame, 20, "r/r0/base_scan", 7)
    assert scan.header.frame_id == "r/r0/base_scan" and scan.header.stamp.nanosec == 7
    assert scan.angle_min == pytest.approx(-math.pi / 2 - 0.3)  # the ray down, first
    assert scan.angle_increment == pytest.approx(math.pi / 2)
    assert scan.range_max == pytest.approx(2.0)
    # down (no hit), right (3rd cell entered at 1.5 cells), up (4.5), left (3.5)
    assert list(scan.ranges) == pytest.approx([math.inf, 0.15, 0.45, 0.35])


def test_markers_colour_frontiers_by_score():
    colors = ros.score_colors(np.array([1.0, 3.0, 2.0, -np.inf]))
    assert colors[0] == pytest.approx(ros.SCORE_COLORMAP[0])
    assert colors[1] == pytest.approx(ros.SCORE_COLORMAP[-1])
    assert colors[2] == pytest.approx(ros.SCORE_COLORMAP[2])  # the middle stop
    assert colors[3] == pytest.approx(ros.SCORE_COLORMAP[0])
    assert ros.score_colors(np.array([5.0, 5.0])) == pytest.approx(
        np.tile(ros.SCORE_COLORMAP[0], (2, 1))
    )
    frame = MapFrame(10, 10, 0.1)
    markers = ros.frontier_markers(np.array([[9, 0], [0, 9]]), np.array([0.0, 1.0]), frame, 0)
    back = ros.deserialize(ros.serialize(markers), ros.MARKERS_TYPE)
    (spheres,) = back.markers
    assert np.allclose([(p.x, p.y) for p in spheres.points], [(0.05, 0.05), (0.95, 0.95)])
    assert spheres.pose.orientation.w == 1.0 and spheres.scale.x == pytest.approx(0.2)
