"""A run's maps, poses, paths, scans, transforms and markers as ROS 2 messages (the
`rosbags` type system and CDR).

The ROS tools see a run in the `map` frame: x to the right along the map's columns, y up
(against the rows), z out of the floor; one cell is `resolution_m` wide and the map's
corner is at the origin. A cell (row, col) therefore sits at
x = (col + 0.5) * resolution_m, y = (rows - 1 - row + 0.5) * resolution_m, and an
OccupancyGrid's data (row-major, row 0 at the origin, i.e. at the bottom) is the map
flipped upside down, so RViz2 and Foxglove draw the map the way this project's figures do.
A heading (yaw) is counter-clockwise from the x axis: a move to the right is 0, a move up
the map (to a smaller row) pi / 2.

Observed maps become -1 unknown, 0 free, 100 occupied; probability maps (the ensemble mean)
0..100; the ensemble variance 0..100 of its largest value, 0.25. Needs the `ros` extra
(`pip install -e '.[ros]'`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.raycast import ray_directions, trace_ray

MAP_FRAME = "map"
GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
PATH_TYPE = "nav_msgs/msg/Path"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
TF_TYPE = "tf2_msgs/msg/TFMessage"
SCAN_TYPE = "sensor_msgs/msg/LaserScan"
MARKERS_TYPE = "visualization_msgs/msg/MarkerArray"
ROS_TYPES = (GRID_TYPE, POSE_TYPE, PATH_TYPE, CLOCK_TYPE, TF_TYPE, SCAN_TYPE, MARKERS_TYPE)
NS_PER_S = 1_000_000_000
MAX_VARIANCE = 0.25  # of a Bernoulli occupancy: the variance grid's 100
OCCUPANCY_SCALE = 100  # an OccupancyGrid's value of certainty
# frontier markers: low to high score along viridis (RGB in [0, 1])
SCORE_COLORMAP = np.array(
    [
        [0.267, 0.005, 0.329],
        [0.229, 0.322, 0.546],
        [0.128, 0.567, 0.551],
        [0.369, 0.789, 0.383],
        [0.993, 0.906, 0.144],
    ]
)
GOAL_COLOR = (0.9, 0.1, 0.1)  # RGB
FRONTIER_MARKER_CELLS = 2.0  # a frontier sphere's diameter, in cells
GOAL_MARKER_CELLS = 5.0


class MissingExtraError(RuntimeError):
    """An optional extra this feature needs is not installed; the message says which."""


@cache
def typestore() -> Any:
    """The ROS 2 Jazzy type store of `rosbags` (also right for Kilted and Rolling: these
    messages have not changed; their RIHS01 hashes are the same)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as error:
        raise MissingExtraError(
            "ROS 2 messages need the ros extra: pip install -e '.[ros]'"
        ) from error
    return get_typestore(Stores.ROS2_JAZZY)


def type_hash(ros_type: str) -> str:
    """The RIHS01 type hash of a message type, e.g. `RIHS01_8d34...` for OccupancyGrid."""
    return typestore().hash_rihs01(ros_type)


def message_definition(ros_type: str) -> str:
    """The concatenated .msg definition (ros2msg schema text, as rosbag2 writes in MCAP)."""
    return typestore().generate_msgdef(ros_type, ros_version=2)[0]


def serialize(message: Any) -> bytes:
    """CDR bytes (little-endian, with its 4-byte encapsulation header) of a rosbags message."""
    return bytes(typestore().serialize_cdr(message, message.__msgtype__))


def deserialize(data: bytes, ros_type: str) -> Any:
    """The rosbags message of CDR bytes."""
    return typestore().deserialize_cdr(data, ros_type)


@dataclass(frozen=True)
class MapFrame:
    """Where the map lies in the `map` frame: its shape in cells and cell size."""

    rows: int
    cols: int
    resolution_m: float = 0.1

    def cell_xy_m(self, cells: np.ndarray) -> np.ndarray:
        """float64 (n, 2) x, y in metres of cell centres int (n, 2) (row, col)."""
        cells = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
        x = (cells[:, 1] + 0.5) * self.resolution_m
        y = (self.rows - 1 - cells[:, 0] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=1)


def observed_values(observed: np.ndarray) -> np.ndarray:
    """int8 (rows, cols) OccupancyGrid values of observed codes: -1 / 0 / 100."""
    values = np.full(observed.shape, -1, dtype=np.int8)
    values[observed == FREE] = 0
    values[observed == OCCUPIED] = 100
    values[observed == UNKNOWN] = -1
    return values


def probability_values(probability: np.ndarray) -> np.ndarray:
    """int8 (rows, cols) OccupancyGrid values 0..100 of occupancy probabilities in [0, 1]."""
    return np.rint(np.clip(probability, 0.0, 1.0) * OCCUPANCY_SCALE).astype(np.int8)


def variance_values(variance: np.ndarray) -> np.ndarray:
    """int8 (rows, cols) OccupancyGrid values of an occupancy variance: round(variance /
    0.25 * 100), clipped to 0..100 (0.25 is a Bernoulli variable's largest variance)."""
    return probability_values(np.asarray(variance, dtype=np.float64) / MAX_VARIANCE)


def heading_rad(previous: tuple[int, int], cell: tuple[int, int]) -> float:
    """The yaw (rad, in the map frame) of a move from cell `previous` to `cell` (row, col)."""
    return math.atan2(-(cell[0] - previous[0]), cell[1] - previous[1])


def occupancy_grid(values: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """nav_msgs/msg/OccupancyGrid of int8 (rows, cols) values in this project's row order."""
    types = typestore().types
    meta = types["nav_msgs/msg/MapMetaData"](
        map_load_time=_time(stamp_ns),
        resolution=float(frame.resolution_m),
        width=int(frame.cols),
        height=int(frame.rows),
        origin=_pose(0.0, 0.0),
    )
    data = np.ascontiguousarray(np.flipud(values), dtype=np.int8).ravel()
    return types[GRID_TYPE](header=_header(stamp_ns), info=meta, data=data)


def pose_stamped(cell: np.ndarray, frame: MapFrame, stamp_ns: int, yaw_rad: float = 0.0) -> Any:
    """geometry_msgs/msg/PoseStamped at a cell's centre, heading `yaw_rad`."""
    x, y = frame.cell_xy_m(np.asarray(cell))[0]
    return typestore().types[POSE_TYPE](header=_header(stamp_ns), pose=_pose(x, y, yaw_rad))


def path(cells: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """nav_msgs/msg/Path through cell centres int (n, 2) (row, col)."""
    poses = [
        typestore().types[POSE_TYPE](header=_header(stamp_ns), pose=_pose(x, y))
        for x, y in frame.cell_xy_m(cells)
    ]
    return typestore().types[PATH_TYPE](header=_header(stamp_ns), poses=poses)


def clock(stamp_ns: int) -> Any:
    """rosgraph_msgs/msg/Clock: the simulated time `stamp_ns`."""
    return typestore().types[CLOCK_TYPE](clock=_time(stamp_ns))


def transform(
    parent: str, child: str, xy_m: tuple[float, float], yaw_rad: float, stamp_ns: int
) -> Any:
    """geometry_msgs/msg/TransformStamped: frame `child` at `xy_m`, turned `yaw_rad`, in
    `parent`."""
    types = typestore().types
    x, y = xy_m
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(stamp_ns, parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=0.0),
            rotation=_quaternion(yaw_rad),
        ),
    )


def tf_message(transforms: list[Any]) -> Any:
    """tf2_msgs/msg/TFMessage of TransformStamped messages."""
    return typestore().types[TF_TYPE](transforms=list(transforms))


@cache
def ray_entry_cells(n_rays: int, range_cells: int) -> np.ndarray:
    """float64 (n_rays, 2 * range_cells + 4): how far (in cells) ray k of `mapex.sensor`
    has gone from its start cell's centre when it enters the m-th cell it walks (0 for the
    start cell; inf past the range). A walk does not depend on where it starts, so one walk
    per ray on an empty map gives every scan's: a ray entering a cell crosses one more row
    or column boundary, the k-th boundary of an axis lying k - 0.5 cells along it."""
    table = np.full((n_rays, 2 * range_cells + 4), np.inf)
    side = 2 * range_cells + 5
    centre = side // 2
    for k, (d_row, d_col) in enumerate(ray_directions(n_rays)):
        cells = trace_ray(side, side, centre, centre, d_row, d_col, float(range_cells))
        crossed = np.abs(cells - centre).astype(np.float64)
        along = np.abs(np.array([d_row, d_col]))
        with np.errstate(divide="ignore", invalid="ignore"):
            entry = np.where(crossed > 0, (crossed - 0.5) / along, 0.0)
        table[k, : len(cells)] = entry.max(axis=1)
    return table


def laser_scan(
    n_cells: np.ndarray,
    hit: np.ndarray,
    yaw_rad: float,
    frame: MapFrame,
    range_cells: int,
    frame_id: str,
    stamp_ns: int,
    scan_time_s: float = 0.0,
) -> Any:
    """sensor_msgs/msg/LaserScan of a `mapex.sensor.Scan`'s rays (n_cells, hit) taken
    with heading `yaw_rad`, in `frame_id` (the robot's, turned by that heading).

    Ray k leaves (row, col) along (sin, cos) of 2 pi k / n, i.e. at -2 pi k / n in the map
    frame: the rays are sent counter-clockwise, from the first one at or after -pi
    relative to the heading. A hit's range is where the ray enters the wall cell (the
    wall's face, within a cell of its centre); a ray without a hit is +inf (REP 117: no
    return within range_max = range_cells * resolution_m)."""
    n = len(n_cells)
    walked = np.asarray(n_cells, dtype=np.int64) - 1
    entry = ray_entry_cells(n, int(range_cells))[np.arange(n), walked]
    ranges = np.where(np.asarray(hit, bool), entry * frame.resolution_m, np.inf)
    by_map_angle = ranges[(n - np.arange(n)) % n]  # the j-th at +2 pi j / n in the map
    increment = 2.0 * math.pi / n
    first = math.ceil((yaw_rad - math.pi) / increment)
    angle_min = first * increment - yaw_rad
    return typestore().types[SCAN_TYPE](
        header=_header(stamp_ns, frame_id),
        angle_min=float(angle_min),
        angle_max=float(angle_min + (n - 1) * increment),
        angle_increment=float(increment),
        time_increment=0.0,
        scan_time=float(scan_time_s),
        range_min=0.0,
        range_max=float(range_cells * frame.resolution_m),
        ranges=by_map_angle[(first + np.arange(n)) % n].astype(np.float32),
        intensities=np.zeros(0, dtype=np.float32),
    )


def score_colors(scores: np.ndarray) -> np.ndarray:
    """float64 (k, 3) RGB of scores along `SCORE_COLORMAP`, lowest to highest finite score
    (a score that is not finite counts as the lowest)."""
    scores = np.asarray(scores, dtype=np.float64)
    finite = np.isfinite(scores)
    if not finite.any():
        return np.tile(SCORE_COLORMAP[0], (len(scores), 1))
    low, high = scores[finite].min(), scores[finite].max()
    spread = high - low if high > low else 1.0
    level = np.where(finite, (scores - low) / spread, 0.0) * (len(SCORE_COLORMAP) - 1)
    stops = np.arange(len(SCORE_COLORMAP))
    return np.stack([np.interp(level, stops, SCORE_COLORMAP[:, c]) for c in range(3)], axis=1)


def frontier_markers(cells: np.ndarray, scores: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """visualization_msgs/msg/MarkerArray: one SPHERE_LIST marker, a sphere per frontier
    cell coloured by its score (`score_colors`), or a DELETE of it when there are none."""
    types = typestore().types
    marker_type = types["visualization_msgs/msg/Marker"]
    cells = np.asarray(cells).reshape(-1, 2)
    if not len(cells):
        return types[MARKERS_TYPE](markers=[_marker("frontiers", marker_type.DELETE, stamp_ns)])
    points = [types["geometry_msgs/msg/Point"](x=x, y=y, z=0.0) for x, y in frame.cell_xy_m(cells)]
    colors = [_color(rgb) for rgb in score_colors(scores)]
    size_m = FRONTIER_MARKER_CELLS * frame.resolution_m
    marker = _marker(
        "frontiers", marker_type.ADD, stamp_ns, marker_type.SPHERE_LIST, _pose(0.0, 0.0),
        size_m, (1.0, 1.0, 1.0), points, colors,
    )  # fmt: skip
    return types[MARKERS_TYPE](markers=[marker])


def goal_markers(goal: tuple[int, int] | None, frame: MapFrame, stamp_ns: int) -> Any:
    """visualization_msgs/msg/MarkerArray: a SPHERE at the goal cell, or a DELETE of it
    when there is no goal."""
    types = typestore().types
    marker_type = types["visualization_msgs/msg/Marker"]
    if goal is None:
        return types[MARKERS_TYPE](markers=[_marker("goal", marker_type.DELETE, stamp_ns)])
    x, y = frame.cell_xy_m(np.asarray(goal))[0]
    size_m = GOAL_MARKER_CELLS * frame.resolution_m
    marker = _marker(
        "goal", marker_type.ADD, stamp_ns, marker_type.SPHERE, _pose(x, y), size_m, GOAL_COLOR
    )
    return types[MARKERS_TYPE](markers=[marker])


def grid_values_in_map_order(message: Any) -> np.ndarray:
    """int8 (rows, cols) of an OccupancyGrid in this project's row order (the inverse of
    `occupancy_grid`; for tests and readers)."""
    rows, cols = int(message.info.height), int(message.info.width)
    return np.flipud(np.asarray(message.data, dtype=np.int8).reshape(rows, cols))


def _time(stamp_ns: int) -> Any:
    return typestore().types["builtin_interfaces/msg/Time"](
        sec=int(stamp_ns // NS_PER_S), nanosec=int(stamp_ns % NS_PER_S)
    )


def _header(stamp_ns: int, frame_id: str = MAP_FRAME) -> Any:
    return typestore().types["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=frame_id)


def _quaternion(yaw_rad: float) -> Any:
    half = 0.5 * float(yaw_rad)
    return typestore().types["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)
    )


def _pose(x: float, y: float, yaw_rad: float = 0.0) -> Any:
    types = typestore().types
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
        orientation=_quaternion(yaw_rad),
    )


def _color(rgb: tuple[float, float, float] | np.ndarray) -> Any:
    r, g, b = (float(c) for c in rgb)
    return typestore().types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=1.0)


def _marker(
    namespace: str,
    action: int,
    stamp_ns: int,
    kind: int = 0,
    pose: Any = None,
    size_m: float = 0.0,
    rgb: tuple[float, float, float] = (1.0, 1.0, 1.0),
    points: list[Any] | None = None,
    colors: list[Any] | None = None,
) -> Any:
    """One visualization_msgs/msg/Marker (id 0 of `namespace`) in the map frame."""
    types = typestore().types
    return types["visualization_msgs/msg/Marker"](
        header=_header(stamp_ns),
        ns=namespace,
        id=0,
        type=kind,
        action=action,
        pose=pose if pose is not None else _pose(0.0, 0.0),
        scale=types["geometry_msgs/msg/Vector3"](x=size_m, y=size_m, z=size_m),
        color=_color(rgb),
        lifetime=types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False,
        points=points or [],
        colors=colors or [],
        texture_resource="",
        texture=types["sensor_msgs/msg/CompressedImage"](
            header=_header(0, ""), format="", data=np.zeros(0, np.uint8)
        ),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=types["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )
