"""A run's maps, poses and paths as Foxglove's own schemas (`foxglove.Grid`, `PoseInFrame`,
`PosesInFrame`, protobuf-encoded by the Foxglove SDK), for Foxglove and Lichtblick.

Same `map` frame as the ROS messages (mapex.interop.ros_messages): the grid's corner at the
origin, rows flipped so y points up. Grids carry RGBA cells drawn like this project's
figures: free white, unknown grey, occupied black; probabilities as grey levels (1 - p).
Needs the Foxglove SDK (`pip install -e '.[foxglove]'`, also part of the `ros` extra).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mapex.grid import observed_to_probability
from mapex.interop.ros_messages import MAP_FRAME, MapFrame, MissingExtraError

FOXGLOVE_TYPES = ("foxglove.Grid", "foxglove.PoseInFrame", "foxglove.PosesInFrame")
FOXGLOVE_ENCODING = "protobuf"  # how the SDK encodes its schemas' messages


def foxglove_messages() -> Any:
    """The `foxglove.messages` module (MissingExtraError when the SDK is not installed)."""
    try:
        import foxglove.messages as messages
    except ImportError as error:
        raise MissingExtraError(
            "Foxglove channels need the foxglove extra: pip install -e '.[foxglove]'"
        ) from error
    return messages


def observed_grid(observed: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """foxglove.Grid of an observed map (codes of mapex.grid)."""
    return probability_grid(observed_to_probability(observed), frame, stamp_ns)


def probability_grid(probability: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """foxglove.Grid of occupancy probabilities in [0, 1] as grey RGBA cells."""
    fm = foxglove_messages()
    grey = np.rint((1.0 - np.clip(probability, 0.0, 1.0)) * 255).astype(np.uint8)
    rgba = np.empty((*grey.shape, 4), dtype=np.uint8)
    rgba[..., :3] = grey[..., None]
    rgba[..., 3] = 255
    fields = [
        fm.PackedElementField(name=name, offset=i, type=fm.PackedElementFieldNumericType.Uint8)
        for i, name in enumerate(("red", "green", "blue", "alpha"))
    ]
    return fm.Grid(
        timestamp=_timestamp(stamp_ns),
        frame_id=MAP_FRAME,
        pose=_pose(0.0, 0.0),
        column_count=int(frame.cols),
        cell_size=fm.Vector2(x=frame.resolution_m, y=frame.resolution_m),
        row_stride=4 * int(frame.cols),
        cell_stride=4,
        fields=fields,
        data=np.flipud(rgba).tobytes(),
    )


def pose_in_frame(cell: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """foxglove.PoseInFrame at a cell's centre."""
    x, y = frame.cell_xy_m(np.asarray(cell))[0]
    return foxglove_messages().PoseInFrame(
        timestamp=_timestamp(stamp_ns), frame_id=MAP_FRAME, pose=_pose(x, y)
    )


def poses_in_frame(cells: np.ndarray, frame: MapFrame, stamp_ns: int) -> Any:
    """foxglove.PosesInFrame through cell centres (a path)."""
    poses = [_pose(x, y) for x, y in frame.cell_xy_m(cells)]
    return foxglove_messages().PosesInFrame(
        timestamp=_timestamp(stamp_ns), frame_id=MAP_FRAME, poses=poses
    )


def _timestamp(stamp_ns: int) -> Any:
    return foxglove_messages().Timestamp(
        int(stamp_ns // 1_000_000_000), int(stamp_ns % 1_000_000_000)
    )


def _pose(x: float, y: float) -> Any:
    fm = foxglove_messages()
    return fm.Pose(
        position=fm.Vector3(x=float(x), y=float(y), z=0.0),
        orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
    )
