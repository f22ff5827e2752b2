"""Gazebo SDF worlds as floor plans (docs/algorithms.md#gazebo-worlds): `FILE.world[@OPTIONS]`.

What a 2D LiDAR at `scan_height_m` would hit becomes wall at 0.1 m: the collision boxes,
upright cylinders and spheres of the static models, with model, link and collision poses
composed (nested models, a saved world's `<state>` poses and model `<scale>` included). An
SDF world has no rooms, so the building's inside is derived from the walls
(`derive_valid_space`). What cannot be rasterised (meshes, heightmaps, polylines, models
pulled in by `<include>`, tilted cylinders) is left out with a one-line warning naming it.

Options after `@`, comma-separated: `scale=F` multiplies every length (datasets scaled on
purpose: the KTH worlds of ../shared/data/kth_sdf were written at twice their size, so
`scale=0.5`), `frame=drop` drops an enclosing rectangle of four walls that a converter drew
around the whole plan. `kth-sdf:ID` is a KTH floor of the shared data with both.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from mapex.config import WorldConfig
from mapex.grid import RESOLUTION_M
from mapex.io_limits import read_bytes
from mapex.worlds.base import World, WorldError, one_line
from mapex.worlds.config import GazeboConfig

log = logging.getLogger("mapex.worlds.gazebo")
DEFAULT_CONFIG = GazeboConfig()

SUFFIXES = (".world", ".sdf")
KTH_SDF_SCALE = 0.5  # the kth_sdf worlds were converted at twice the floors' size
# a cell's centre within half a cell of a shape marks it; thin walls get at least this
# half-width, so that a diagonal wall is 4-connected and no ray or path slips through it
MIN_HALF_WIDTH_CELLS = math.sqrt(2) / 2
# reaches are this much (0.1 mm) short of their value, so that a cell centre exactly half a
# cell from a wall's face (a grid-aligned plan) is decided by the rule, not by rounding noise
_TIE_M = 1e-4
_UPRIGHT_TOLERANCE = 1e-6  # |cos| of a shape's axis to the vertical that counts as upright
_UNSUPPORTED = ("mesh", "heightmap", "polyline", "capsule", "ellipsoid", "image")


@dataclass(frozen=True)
class GazeboOptions:
    """What follows `@` in a spec: a length factor and whether to drop a converter's frame."""

    scale: float = 1.0
    drop_frame: bool = False


@dataclass(frozen=True)
class Transform:
    """A rigid 3-D pose: rotation (3, 3) and translation (3,), in the world's unscaled metres."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def then(self, child: Transform, scale: np.ndarray | None = None) -> Transform:
        """The pose of `child`, given in this frame (its offset multiplied by `scale`)."""
        offset = child.translation if scale is None else child.translation * scale
        return Transform(self.rotation @ child.rotation, self.translation + self.rotation @ offset)


@dataclass(frozen=True)
class Footprint:
    """Where one geometry cuts the scan plane, in metres: a convex polygon (k, 2) of (x, y)
    corners counter-clockwise, or a disc (`centre`, `radius_m`)."""

    name: str
    polygon: np.ndarray | None = None
    centre: tuple[float, float] = (0.0, 0.0)
    radius_m: float = 0.0

    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max)."""
        if self.polygon is None:
            x, y = self.centre
            r = self.radius_m
            return x - r, y - r, x + r, y + r
        (x0, y0), (x1, y1) = self.polygon.min(axis=0), self.polygon.max(axis=0)
        return float(x0), float(y0), float(x1), float(y1)

    def scaled(self, factor: float) -> Footprint:
        if self.polygon is None:
            centre = (self.centre[0] * factor, self.centre[1] * factor)
            return Footprint(self.name, None, centre, self.radius_m * factor)
        return Footprint(self.name, self.polygon * factor)


def load_gazebo_world(
    spec: str, max_cells: int = WorldConfig().max_cells, name: str | None = None
) -> World:
    """The world of `FILE.world[@OPTIONS]` at 0.1 m per cell, named after the file; a one-line
    WorldError when the file cannot be read, holds no wall, or would exceed `max_cells`."""
    path_text, options = parse_gazebo_spec(spec)
    return gazebo_world(Path(path_text), options, max_cells, name)


def gazebo_world(
    path: Path,
    options: GazeboOptions = GazeboOptions(),
    max_cells: int = WorldConfig().max_cells,
    name: str | None = None,
    config: GazeboConfig = DEFAULT_CONFIG,
) -> World:
    """The world of the SDF file at `path` (see the module docstring)."""
    footprints = read_footprints(path, config, options.scale)
    footprints = [f.scaled(options.scale) for f in footprints]
    if options.drop_frame:
        footprints = drop_enclosing_frame(footprints, config.frame_tolerance_m)
    if not footprints:
        raise WorldError(f"{path}: no wall crosses the scan plane ({config.scan_height_m} m)")
    walls = rasterise(footprints, max_cells, config.margin_cells)
    world_name = name or path.stem
    return World(world_name, walls, derive_valid_space(walls, config, world_name))


def parse_gazebo_spec(spec: str) -> tuple[str, GazeboOptions]:
    """(file path, options) of `FILE.world[@scale=F,frame=drop]`; a one-line WorldError for an
    option it does not know or a factor that is not a positive number."""
    path, at, text = spec.rpartition("@")
    if not at or "=" not in text:
        return spec, GazeboOptions()
    scale, drop_frame = 1.0, False
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, _, value = item.partition("=")
        if key == "scale":
            try:
                scale = float(value)
            except ValueError:
                scale = math.nan
            if not (math.isfinite(scale) and scale > 0):
                raise WorldError(f"{spec}: scale={value!r} must be a positive number")
        elif key == "frame" and value in ("drop", "keep"):
            drop_frame = value == "drop"
        else:
            raise WorldError(f"{spec}: unknown option {item!r} (scale=F, frame=drop|keep)")
    return path, GazeboOptions(scale, drop_frame)


def read_footprints(
    path: Path, config: GazeboConfig = DEFAULT_CONFIG, scale: float = 1.0
) -> list[Footprint]:
    """Every footprint of the static models of the SDF file at `path` on the scan plane, in
    the file's own metres (`scale` times them is the world's: the scan plane lies at
    `scan_height_m / scale` in the file)."""
    try:
        root = ET.fromstring(read_bytes(path, WorldConfig().max_file_bytes))
    except ET.ParseError as error:
        raise WorldError(f"{path}: not an SDF file ({one_line(error)})") from None
    except OSError as error:
        raise WorldError(f"{path}: {one_line(error)}") from None
    if root.tag != "sdf":
        raise WorldError(f"{path}: not an SDF file (its root element is <{root.tag}>)")
    reader = _SdfReader(path, config, config.scan_height_m / scale)
    for world in root.findall("world") or [root]:
        reader.read_world(world)
    return reader.footprints


class _SdfReader:
    """Walks an SDF tree, collecting footprints and warning once about each thing left out."""

    def __init__(self, path: Path, config: GazeboConfig, scan_height: float) -> None:
        self.path = path
        self.config = config
        self.scan_height = scan_height  # in the file's metres
        self.footprints: list[Footprint] = []
        self.state: dict[str, ET.Element] = {}

    def warn(self, message: str) -> None:
        log.warning("%s: %s", self.path.name, message)

    def read_world(self, world: ET.Element) -> None:
        self.state = {m.get("name", ""): m for m in world.findall("state/model")}
        for include in world.findall("include"):
            uri = include.findtext("uri", "?").strip()
            self.warn(f"<include> of {uri!r} left out (included models are not followed)")
        for model in world.findall("model"):
            self.read_model(model, Transform(), np.ones(3), static=False, prefix="")

    def read_model(
        self, model: ET.Element, parent: Transform, scale: np.ndarray, static: bool, prefix: str
    ) -> None:
        name = prefix + model.get("name", "?")
        static = static or _is_true(model.findtext("static"))
        state = self.state.get(name) if not prefix else None
        pose_element = model.find("pose")
        if state is not None and state.find("pose") is not None:
            pose_element = state.find("pose")  # a saved world's state moves its models
        frame = parent.then(self._pose(pose_element, name), scale)
        own_scale = _scale(state.findtext("scale") if state is not None else None, name, self)
        own_scale = own_scale * _scale(model.findtext("scale"), name, self)
        if not static:
            if model.findall(".//collision"):
                self.warn(f"model {name!r} is not static: left out (a robot or a movable object)")
            return
        scale = scale * own_scale
        for link in model.findall("link"):
            link_name = f"{name}::{link.get('name', '?')}"
            link_frame = frame.then(self._pose(link.find("pose"), link_name), scale)
            for collision in link.findall("collision"):
                label = f"{link_name}::{collision.get('name', '?')}"
                pose = link_frame.then(self._pose(collision.find("pose"), label), scale)
                self.read_geometry(collision.find("geometry"), pose, scale, label)
        for nested in model.findall("model"):
            self.read_model(nested, frame, scale, static, prefix=f"{name}::")

    def read_geometry(
        self, geometry: ET.Element | None, pose: Transform, scale: np.ndarray, label: str
    ) -> None:
        if geometry is None or len(geometry) == 0:
            return
        shape = geometry[0]
        if shape.tag == "box":
            size = _numbers(shape.findtext("size"), 3, f"{label} box size", self) * scale
            self._add(box_footprint(label, pose, size, self.scan_height))
        elif shape.tag == "cylinder":
            radius = _number(shape.findtext("radius"), f"{label} radius", self) * scale[0]
            length = _number(shape.findtext("length"), f"{label} length", self) * scale[2]
            if abs(abs(pose.rotation[2, 2]) - 1) > _UPRIGHT_TOLERANCE:
                self.warn(f"{label}: a tilted cylinder cannot be rasterised: left out")
                return
            self._add(disc_footprint(label, pose, radius, length, self.scan_height))
        elif shape.tag == "sphere":
            radius = _number(shape.findtext("radius"), f"{label} radius", self) * scale[0]
            self._add(sphere_footprint(label, pose, radius, self.scan_height))
        elif shape.tag in _UNSUPPORTED:
            self.warn(f"{label}: <{shape.tag}> geometry cannot be rasterised: left out")
        elif shape.tag not in ("plane", "empty"):  # the ground plane is no wall
            self.warn(f"{label}: unknown geometry <{shape.tag}>: left out")

    def _add(self, footprint: Footprint | None) -> None:
        if footprint is None:
            return
        if len(self.footprints) >= self.config.max_geometries:
            raise WorldError(
                f"{self.path}: more than {self.config.max_geometries:,} wall geometries "
                "(--set gazebo.max_geometries does not reach a world file; split it)"
            )
        self.footprints.append(footprint)

    def _pose(self, element: ET.Element | None, label: str) -> Transform:
        if element is None or not (element.text or "").strip():
            return Transform()
        relative_to = element.get("relative_to") or element.get("frame")
        if relative_to:
            self.warn(f"{label}: pose relative to {relative_to!r} read as relative to its parent")
        values = (element.text or "").split()
        if element.get("rotation_format") == "quat_xyzw":
            numbers = _numbers(element.text, 7, f"{label} pose", self)
            return Transform(_quaternion_matrix(numbers[3:]), numbers[:3])
        numbers = _numbers(" ".join(values), 6, f"{label} pose", self)
        angles = np.radians(numbers[3:]) if _is_true(element.get("degrees")) else numbers[3:]
        return Transform(_euler_matrix(*angles), numbers[:3])


def box_footprint(
    label: str, pose: Transform, size: np.ndarray, scan_height_m: float
) -> Footprint | None:
    """The footprint of a box of `size` (x, y, z metres) centred at `pose`, or None when it
    does not reach the scan plane. An upright box cuts it in a rectangle; a tilted one is
    taken whole (the convex hull of its corners seen from above)."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    corners = pose.translation + (signs * size / 2) @ pose.rotation.T
    if not corners[:, 2].min() <= scan_height_m <= corners[:, 2].max():
        return None
    return Footprint(label, convex_hull(corners[:, :2]))


def disc_footprint(
    label: str, pose: Transform, radius_m: float, length_m: float, scan_height_m: float
) -> Footprint | None:
    """The disc an upright cylinder cuts from the scan plane (None if it does not reach it)."""
    if abs(pose.translation[2] - scan_height_m) > length_m / 2:
        return None
    return Footprint(
        label, None, (float(pose.translation[0]), float(pose.translation[1])), radius_m
    )


def sphere_footprint(
    label: str, pose: Transform, radius_m: float, scan_height_m: float
) -> Footprint | None:
    """The disc a sphere cuts from the scan plane (None if it does not reach it)."""
    height = abs(pose.translation[2] - scan_height_m)
    if height > radius_m:
        return None
    centre = (float(pose.translation[0]), float(pose.translation[1]))
    return Footprint(label, None, centre, math.sqrt(radius_m**2 - height**2))


def drop_enclosing_frame(footprints: list[Footprint], tolerance_m: float) -> list[Footprint]:
    """`footprints` without a converter's frame: four walls, each running along a whole side
    of the plan's bounding box (within `tolerance_m`). When no such four walls exist the
    plan is kept whole, with a warning."""
    bounds = np.array([f.bounds() for f in footprints])
    x0, y0 = bounds[:, 0].min(), bounds[:, 1].min()
    x1, y1 = bounds[:, 2].max(), bounds[:, 3].max()
    sides = [  # (index of the bound that must sit on the side, its value, along-axis)
        (1, y0, 0), (3, y1, 0), (0, x0, 1), (2, x1, 1),
    ]  # fmt: skip
    frame = []
    for bound, value, along in sides:
        span = (x1 - x0) if along == 0 else (y1 - y0)
        across = 1 - along  # the bound across the side, e.g. y for a horizontal side
        candidates = [
            k
            for k, (f, b) in enumerate(zip(footprints, bounds, strict=True))
            if f.polygon is not None
            and abs(b[bound] - value) <= tolerance_m
            and b[across + 2] - b[across] <= 2 * tolerance_m
            and b[along + 2] - b[along] >= span - 2 * tolerance_m
        ]
        if not candidates:
            log.warning("frame=drop: no enclosing frame of four walls found: every wall kept")
            return footprints
        frame.append(candidates[0])
    return [f for k, f in enumerate(footprints) if k not in set(frame)]


def rasterise(footprints: list[Footprint], max_cells: int, margin_cells: int) -> np.ndarray:
    """Walls, bool (rows, cols) at 0.1 m, row 0 at the top (largest y): a cell is a wall when
    its centre lies within half a cell of a footprint (thin walls: `MIN_HALF_WIDTH_CELLS`).
    The grid covers every footprint with `margin_cells` of free space around."""
    res = RESOLUTION_M
    bounds = np.array([f.bounds() for f in footprints])
    x0 = bounds[:, 0].min() - margin_cells * res
    y1 = bounds[:, 3].max() + margin_cells * res
    cols = math.ceil((bounds[:, 2].max() + margin_cells * res - x0) / res)
    rows = math.ceil((y1 - (bounds[:, 1].min() - margin_cells * res)) / res)
    if rows * cols > max_cells:
        raise WorldError(
            f"the plan needs {rows * cols:,} cells ({rows} x {cols}), above the limit of "
            f"{max_cells:,}: raise it with --set world.max_cells={rows * cols}"
        )
    walls = np.zeros((rows, cols), dtype=bool)
    for footprint, (bx0, by0, bx1, by1) in zip(footprints, bounds, strict=True):
        reach = MIN_HALF_WIDTH_CELLS * res
        c0, c1 = max(int((bx0 - reach - x0) / res), 0), min(int((bx1 + reach - x0) / res) + 1, cols)
        r0, r1 = max(int((y1 - by1 - reach) / res), 0), min(int((y1 - by0 + reach) / res) + 1, rows)
        if c0 >= c1 or r0 >= r1:
            continue
        x = x0 + (np.arange(c0, c1) + 0.5) * res
        y = y1 - (np.arange(r0, r1) + 0.5) * res
        walls[r0:r1, c0:c1] |= _covered(footprint, x[None, :], y[:, None], res)
    return walls


def _covered(footprint: Footprint, x: np.ndarray, y: np.ndarray, res: float) -> np.ndarray:
    """Which cell centres (x, y broadcast) lie within half a cell of `footprint`."""
    if footprint.polygon is None:
        cx, cy = footprint.centre
        return np.hypot(x - cx, y - cy) <= footprint.radius_m + res / 2 - _TIE_M
    corners = footprint.polygon
    edges = np.roll(corners, -1, axis=0) - corners
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)  # outward for counter-clockwise
    lengths = np.hypot(*normals.T)
    keep = lengths > 1e-12
    normals, corners = normals[keep] / lengths[keep, None], corners[keep]
    if len(normals) < 3:  # a degenerate footprint (a box of no area): a segment or a point
        return _near_segment(footprint.polygon, x, y, MIN_HALF_WIDTH_CELLS * res - _TIE_M)
    width = _min_width(footprint.polygon, normals)
    reach = max(res / 2, MIN_HALF_WIDTH_CELLS * res - width / 2) - _TIE_M
    distance = np.full(np.broadcast_shapes(x.shape, y.shape), -np.inf)
    for (nx, ny), (px, py) in zip(normals, corners, strict=True):
        distance = np.maximum(distance, nx * (x - px) + ny * (y - py))
    return distance <= reach


def _min_width(polygon: np.ndarray, normals: np.ndarray) -> float:
    """The convex polygon's smallest width (over its edge normals)."""
    projected = polygon @ normals.T
    return float((projected.max(axis=0) - projected.min(axis=0)).min())


def _near_segment(points: np.ndarray, x: np.ndarray, y: np.ndarray, reach: float) -> np.ndarray:
    """Cell centres within `reach` of the segment spanned by `points` (a degenerate box)."""
    start, end = points.min(axis=0), points.max(axis=0)
    if np.allclose(start, end):
        return np.hypot(x - start[0], y - start[1]) <= reach
    first, last = (
        points[np.argmin(points @ (end - start))],
        points[np.argmax(points @ (end - start))],
    )
    direction = last - first
    t = np.clip(
        ((x - first[0]) * direction[0] + (y - first[1]) * direction[1]) / (direction @ direction),
        0,
        1,
    )
    return np.hypot(x - first[0] - t * direction[0], y - first[1] - t * direction[1]) <= reach


def derive_valid_space(walls: np.ndarray, config: GazeboConfig, name: str = "") -> np.ndarray:
    """The building's rooms (bool, like a KTH map's valid space) from its walls alone.

    Doors and windows are gaps in the walls, so the outside is what is reachable from the
    map's border once gaps up to 2 x `gap_closing_cells` wide are closed, grown back to the
    walls; every other free region of at least `min_room_cells` is a room, and the walls
    within `valid_wall_cells` of a room belong to it. A plan whose walls enclose nothing
    gets every free cell, with a warning."""
    closing = config.gap_closing_cells
    pad = closing + 1  # free space around the map, so that the outside always has room
    padded = np.pad(walls, pad, constant_values=False)
    labels, _ = ndimage.label(ndimage.distance_transform_edt(~padded) > closing)
    seeds = labels == labels[0, 0]  # the padding's corner is outside
    outside = (ndimage.distance_transform_edt(~seeds) <= closing)[pad:-pad, pad:-pad]
    inside = ~walls & ~outside
    labels, count = ndimage.label(inside)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    inside = (sizes >= config.min_room_cells)[labels] & (labels > 0)
    if not inside.any():
        log.warning("%s: the walls enclose no room: every free cell is valid space", name)
        return ~walls
    near_room = ndimage.distance_transform_edt(~inside) <= config.valid_wall_cells
    return inside | (walls & near_room)


def convex_hull(points: np.ndarray) -> np.ndarray:
    """The convex hull (k, 2) of 2-D points, counter-clockwise (Andrew's monotone chain)."""
    unique = np.unique(np.round(points, 12), axis=0)
    if len(unique) <= 2:
        return unique
    ordered = sorted(map(tuple, unique))

    def half(sequence: list[tuple[float, float]]) -> list[tuple[float, float]]:
        chain: list[tuple[float, float]] = []
        for p in sequence:
            while len(chain) >= 2 and _cross(chain[-2], chain[-1], p) <= 0:
                chain.pop()
            chain.append(p)
        return chain

    lower, upper = half(ordered), half(ordered[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _euler_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """SDF's rotation: yaw about z, then pitch about y, then roll about x (Rz Ry Rx)."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _quaternion_matrix(xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = xyzw / max(np.linalg.norm(xyzw), 1e-12)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _is_true(text: str | None) -> bool:
    return (text or "").strip().lower() in ("1", "true")


def _numbers(text: str | None, count: int, what: str, reader: _SdfReader) -> np.ndarray:
    try:
        values = np.array([float(v) for v in (text or "").split()], dtype=np.float64)
    except ValueError:
        values = np.array([])
    if values.shape != (count,) or not np.isfinite(values).all():
        raise WorldError(f"{reader.path}: {what} {text!r} is not {count} finite numbers")
    return values


def _number(text: str | None, what: str, reader: _SdfReader) -> float:
    return float(_numbers(text, 1, what, reader)[0])


def _scale(text: str | None, name: str, reader: _SdfReader) -> np.ndarray:
    if text is None or not text.strip():
        return np.ones(3)
    values = _numbers(text, 3, f"model {name!r} scale", reader)
    if (values <= 0).any():
        raise WorldError(f"{reader.path}: model {name!r} scale {text!r} must be positive")
    return values


def load_kth_sdf_world(floor_id: str, max_cells: int = WorldConfig().max_cells) -> World:
    """The KTH floor `floor_id` of ../shared/data/kth_sdf (train/ or check/) at its real size
    with the converter's frame dropped, named `floor_id`; a one-line WorldError when there
    is no such floor."""
    from mapex.worlds.data import KTH_SDF_DIR, KTH_SDF_SPLITS

    if not floor_id or not all(c.isalnum() or c in "_-" for c in floor_id):
        raise WorldError(f"bad KTH floor id {floor_id!r}: letters, digits, '_' and '-' only")
    for split in KTH_SDF_SPLITS:
        path = KTH_SDF_DIR / split / f"{floor_id}.world"
        if path.is_file():
            options = GazeboOptions(scale=KTH_SDF_SCALE, drop_frame=True)
            return gazebo_world(path, options, max_cells, name=floor_id)
    raise WorldError(f"no KTH floor {floor_id!r} in {KTH_SDF_DIR}/{{{','.join(KTH_SDF_SPLITS)}}}")
