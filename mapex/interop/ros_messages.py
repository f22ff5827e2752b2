"""A run's maps, poses and paths as ROS 2 messages (the `rosbags` type system and CDR).

The ROS tools see a run in the `map` frame: x to the right along the map's columns, y up
(against the rows), z out of the floor; one cell is `resolution_m` wide and the map's
corner is at the origin. A cell (row, col) therefore sits at
x = (col + 0.5) * resolution_m, y = (rows - 1 - row + 0.5) * resolution_m, and an
OccupancyGrid's data (row-major, row 0 at the origin, i.e. at the bottom) is the map
flipped upside down, so RViz2 and Foxglove draw the map the way this project's figures do.

Observed maps become -1 unknown, 0 free, 100 occupied; probability maps (the ensemble mean)
0..100. Needs the `ros` extra (`pip install -e '.[ros]'`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from mapex.grid import FREE, OCCUPIED, UNKNOWN

MAP_FRAME = "map"
GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
PATH_TYPE = "nav_msgs/msg/Path"
ROS_TYPES = (GRID_TYPE, POSE_TYPE, PATH_TYPE)


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
    return np.rint(np.clip(probability, 0.0, 1.0) * 100).astype(np.int8)


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


def pose_stamped(cell: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """geometry_msgs/msg/PoseStamped at a cell's centre (no heading: the robot is a point)."""
    x, y = frame.cell_xy_m(np.asarray(cell))[0]
    return typestore().types[POSE_TYPE](header=_header(stamp_ns), pose=_pose(x, y))


def path(cells: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """nav_msgs/msg/Path through cell centres int (n, 2) (row, col)."""
    poses = [
        typestore().types[POSE_TYPE](header=_header(stamp_ns), pose=_pose(x, y))
        for x, y in frame.cell_xy_m(cells)
    ]
    return typestore().types[PATH_TYPE](header=_header(stamp_ns), poses=poses)


def grid_values_in_map_order(message: Any) -> np.ndarray:
    """int8 (rows, cols) of an OccupancyGrid in this project's row order (the inverse of
    `occupancy_grid`; for tests and readers)."""
    rows, cols = int(message.info.height), int(message.info.width)
    return np.flipud(np.asarray(message.data, dtype=np.int8).reshape(rows, cols))


def _time(stamp_ns: int) -> Any:
    return typestore().types["builtin_interfaces/msg/Time"](
        sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
    )


def _header(stamp_ns: int) -> Any:
    return typestore().types["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=MAP_FRAME)


def _pose(x: float, y: float) -> Any:
    types = typestore().types
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
