"""Gazebo SDF worlds: pose composition, rotation, scale, what cannot be rasterised, the
derived inside, one-line errors, and agreement with the authors' rasters of two KTH floors."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage
from sdf_worlds import box_link, model, room_links, world, write

from mapex.grid import RESOLUTION_M
from mapex.worlds import WorldError, load_world
from mapex.worlds.config import GazeboConfig
from mapex.worlds.data import KTH_SDF_DIR, KTH_VALIDATION_MAPS
from mapex.worlds.gazebo import convex_hull, derive_valid_space, parse_gazebo_spec

NEEDS_KTH_SDF = pytest.mark.skipif(
    not (KTH_SDF_DIR / "check").is_dir(), reason="../shared/data/kth_sdf is not present"
)


def load(tmp_path: Path, text: str, options: str = "") -> object:
    path = write(tmp_path / "hand.world", text)
    return load_world(f"{path}{options}")


def wall_cells_metres(w) -> np.ndarray:
    """Centres (x, y) in metres of the wall cells, with the raster's origin at its
    top-left corner: x = column, y = -row."""
    rows, cols = np.nonzero(w.occupancy)
    return np.stack([(cols + 0.5) * RESOLUTION_M, -(rows + 0.5) * RESOLUTION_M], axis=1)


def test_model_link_and_collision_poses_are_composed(tmp_path) -> None:
    # model at (5, 1) turned by 90 degrees; link 2 m along the model's x; collision 1 m
    # along the link's x, turned by another 90 degrees: a 4 m wall along x centred at
    # (5, 1) + R(90)(2 + 1, 0) = (5, 4), and a reference wall placed there directly.
    nested = model(
        "m",
        "5.03 1.02 0 0 0 1.5707963",
        box_link("l", "2 0 0 0 0 0", "4 0.1 2", "1 0 1 0 0 1.5707963"),
    )
    direct = model(
        "d", "0 0 0 0 0 0", box_link("l", "5.03 4.02 0 0 0 0", "4 0.1 2", "0 0 1 0 0 3.1415927")
    )
    anchor = model("a", "0 0 0 0 0 0", box_link("p", "0 0 0 0 0 0", "0.1 0.1 2"))
    composed = load(tmp_path, world(nested, anchor))
    reference = load(tmp_path, world(direct, anchor))
    assert np.array_equal(composed.occupancy, reference.occupancy)
    cells = wall_cells_metres(composed)
    wall = cells[cells[:, 0] > 1.0]  # the anchor post sits at the raster's left edge
    span = wall.max(axis=0) - wall.min(axis=0)
    assert span[0] == pytest.approx(4.0, abs=0.25) and span[1] <= 0.25  # along x, thin


def test_a_rotated_wall_is_covered_and_four_connected(tmp_path) -> None:
    angle = math.radians(30)
    links = box_link("w", f"0 0 0 0 0 {angle}", "6 0.05 2")
    w = load(tmp_path, world(model("m", "0 0 0 0 0 0", links)))
    rows, cols = w.shape
    # every point of the wall's centre line lies in a wall cell; the raster's top-left corner
    # is 2 margin cells beyond the wall's bounding box
    half_x = 3 * math.cos(angle) + 0.025 * math.sin(angle) + 2 * RESOLUTION_M
    half_y = 3 * math.sin(angle) + 0.025 * math.cos(angle) + 2 * RESOLUTION_M
    for s in np.linspace(-2.95, 2.95, 200):
        x, y = half_x + s * math.cos(angle), half_y - s * math.sin(angle)  # y down the rows
        assert w.occupancy[int(y / RESOLUTION_M), int(x / RESOLUTION_M)], s
    # one 4-connected wall: no diagonal step that a ray or an 8-connected path slips through
    _, pieces = ndimage.label(w.occupancy)  # 4-connectivity
    assert pieces == 1


def test_scale_option_and_model_scale(tmp_path) -> None:
    links = box_link("w", "0 0 0 0 0 0", "8 0.1 2")
    full = load(tmp_path, world(model("m", "0 0 0 0 0 0", links)))
    half = load(tmp_path, world(model("m", "0 0 0 0 0 0", links)), "@scale=0.5")
    state = '<state world_name="default"><model name="m"><scale>2 2 1</scale></model></state>'
    doubled = load(tmp_path, world(model("m", "0 0 0 0 0 0", links), state=state))

    def length(w) -> float:
        cells = wall_cells_metres(w)
        return float(np.ptp(cells[:, 0]))

    assert length(full) == pytest.approx(8.0, abs=0.25)
    assert length(half) == pytest.approx(4.0, abs=0.25)
    assert length(doubled) == pytest.approx(16.0, abs=0.25)


def test_a_saved_state_moves_a_model(tmp_path) -> None:
    links = box_link("w", "0 0 0 0 0 0", "2 0.1 2")
    anchor = model("a", "0 0 0 0 0 0", box_link("p", "0 0 0 0 0 0", "0.1 0.1 2"))
    state = '<state world_name="default"><model name="m"><pose>6 0 0 0 0 0</pose></model></state>'
    moved = load(tmp_path, world(anchor, model("m", "0 0 0 0 0 0", links), state=state))
    assert wall_cells_metres(moved)[:, 0].max() == pytest.approx(7.0 + 0.2, abs=0.2)


def test_what_cannot_be_rasterised_is_named_in_one_line(tmp_path, caplog) -> None:
    mesh = """<link name="statue"><collision name="c"><geometry><mesh><uri>model://x.dae</uri>
      </mesh></geometry></collision></link>"""
    tilted = """<link name="log"><pose>0 0 0 1.2 0 0</pose><collision name="c"><geometry>
      <cylinder><radius>0.2</radius><length>3</length></cylinder></geometry></collision></link>"""
    pillar = """<link name="pillar"><pose>3 3 0 0 0 0</pose><collision name="c"><geometry>
      <cylinder><radius>0.5</radius><length>2</length></cylinder></geometry></collision></link>"""
    robot = model(
        "robot", "1 1 0 0 0 0", box_link("base", "0 0 0 0 0 0", "0.4 0.4 0.3"), static=False
    )
    include = "<include><uri>model://bookshelf</uri></include>"
    text = world(
        model("m", "0 0 0 0 0 0", mesh + tilted + pillar + room_links(10, 8)),
        robot,
        include=include,
    )
    with caplog.at_level(logging.WARNING, logger="mapex.worlds.gazebo"):
        w = load(tmp_path, text)
    messages = [r.getMessage() for r in caplog.records]
    assert all("\n" not in m for m in messages)
    for named in ("m::statue::c: <mesh>", "m::log::c: a tilted cylinder", "'robot' is not static",
                  "'model://bookshelf'"):  # fmt: skip
        assert any(named in m for m in messages), (named, messages)
    # the upright cylinder is a disc of radius 0.5 m (+ half a cell)
    cells = wall_cells_metres(w)
    near_pillar = cells[np.hypot(*(cells - cells.mean(axis=0)).T) < 100]
    assert len(near_pillar)  # the pillar is drawn: checked by its area below
    disc = np.pi * (0.5 + RESOLUTION_M / 2) ** 2 / RESOLUTION_M**2
    room_walls = load(tmp_path, world(model("m", "0 0 0 0 0 0", room_links(10, 8)))).occupancy.sum()
    assert w.occupancy.sum() - room_walls == pytest.approx(disc, rel=0.15)


def test_the_inside_is_the_room_behind_its_door(tmp_path) -> None:
    w = load(tmp_path, world(model("m", "0 0 0 0 0 0", room_links(10, 8, door_m=1.0))))
    rows, cols = w.shape
    assert w.valid_space[rows // 2, cols // 2]  # the room
    assert not w.valid_space[0, 0] and not w.valid_space[-1, -1]  # the margin outside
    room_cells = (10 - 0.1) * (8 - 0.1) / RESOLUTION_M**2
    inside = w.valid_space & ~w.occupancy
    assert inside.sum() == pytest.approx(room_cells, rel=0.05)


def test_a_plan_that_encloses_nothing_is_all_valid(tmp_path, caplog) -> None:
    links = box_link("w", "0 0 0 0 0 0", "8 0.1 2")
    with caplog.at_level(logging.WARNING, logger="mapex.worlds.gazebo"):
        w = load(tmp_path, world(model("m", "0 0 0 0 0 0", links)))
    assert np.array_equal(w.valid_space, ~w.occupancy)
    assert any("enclose no room" in r.getMessage() for r in caplog.records)


def test_a_converters_frame_is_dropped_on_request(tmp_path, caplog) -> None:
    frame = "".join(
        box_link(name, pose, size)
        for name, pose, size in [
            ("f_top", "0 10 0 0 0 0", "30 0.1 2"),
            ("f_bottom", "0 -10 0 0 0 0", "30 0.1 2"),
            ("f_left", "-15 0 0 0 0 0", "0.1 20 2"),
            ("f_right", "15 0 0 0 0 0", "0.1 20 2"),
        ]
    )
    text = world(model("m", "0 0 0 0 0 0", room_links(10, 8) + frame))
    kept = load(tmp_path, text)
    dropped = load(tmp_path, text, "@frame=drop")
    assert kept.shape[1] > 300 and dropped.shape[1] < 110  # 30 m frame gone: the 10 m room
    # with its frame the yard between frame and room reads as inside; without it, not
    assert kept.valid_space.sum() > 2 * dropped.valid_space.sum()
    with caplog.at_level(logging.WARNING, logger="mapex.worlds.gazebo"):
        load(tmp_path, world(model("m", "0 0 0 0 0 0", room_links(10, 8))), "@frame=drop")
    assert any("no enclosing frame" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    "text, options, message",
    [
        ("not xml <", "", "not an SDF file"),
        ("<robot/>", "", "its root element is <robot>"),
        (world(model("m", "0 0 x", box_link("l", "0 0 0 0 0 0", "1 1 1"))), "", "pose"),
        (world(model("m", "0 0 0 0 0 0", box_link("l", "0 0 0 0 0 0", "1 1"))), "", "box size"),
        (
            world(model("m", "0 0 0 0 0 0", box_link("l", "0 0 0 0 0 0", "1 1 1"))),
            "@scale=0",
            "scale",
        ),
        (
            world(model("m", "0 0 0 0 0 0", box_link("l", "0 0 0 0 0 0", "1 1 1"))),
            "@zoom=2",
            "unknown option",
        ),
        (world(), "", "no wall crosses the scan plane"),
        (world(model("m", "0 0 0 0 0 0", box_link("l", "0 0 5 0 0 0", "1 1 1"))), "", "scan plane"),
    ],
)
def test_bad_worlds_are_one_line_errors(tmp_path, text, options, message) -> None:
    with pytest.raises(WorldError, match=message) as caught:
        load(tmp_path, text, options)
    assert "\n" not in str(caught.value)


def test_a_plan_too_large_is_refused_before_rasterising(tmp_path) -> None:
    links = box_link("w", "0 0 0 0 0 0", "10000 0.1 2") + box_link(
        "v", "0 0 0 0 0 0", "0.1 10000 2"
    )
    with pytest.raises(WorldError, match="world.max_cells"):
        load(tmp_path, world(model("m", "0 0 0 0 0 0", links)))


def test_missing_and_odd_files_are_one_line_errors(tmp_path) -> None:
    with pytest.raises(WorldError, match="No such file"):
        load_world(str(tmp_path / "none.world"))
    (tmp_path / "dir.world").mkdir()
    with pytest.raises(WorldError, match="not a regular file"):
        load_world(str(tmp_path / "dir.world"))
    (tmp_path / "zero.world").symlink_to("/dev/zero")
    with pytest.raises(WorldError, match="not a regular file"):
        load_world(str(tmp_path / "zero.world"))  # never read


def test_spec_options_parse() -> None:
    assert parse_gazebo_spec("a/b.world")[1].scale == 1.0
    path, options = parse_gazebo_spec("a/b@c.world@scale=0.5,frame=drop")
    assert path == "a/b@c.world" and options.scale == 0.5 and options.drop_frame


def test_convex_hull_is_counter_clockwise() -> None:
    hull = convex_hull(np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [1, 1]], float))
    assert len(hull) == 4
    area = 0.5 * np.sum(hull[:, 0] * np.roll(hull[:, 1], -1) - np.roll(hull[:, 0], -1) * hull[:, 1])
    assert area == pytest.approx(1.0)


def test_derived_valid_space_keeps_a_courtyard_behind_a_wide_gate_out() -> None:
    walls = np.zeros((120, 180), dtype=bool)
    walls[10, 10:110] = walls[109, 10:110] = walls[10:110, 10] = walls[10:110, 109] = True
    walls[10, 130:170] = walls[50, 130:170] = walls[10:51, 130] = walls[10:51, 169] = True
    walls[109, 50:80] = False  # a 3 m gate: wider than twice the 1.2 m gap closing
    valid = derive_valid_space(walls, GazeboConfig())
    assert not valid[60, 60] and valid[30, 150]  # open through the gate; a closed room
    walls[109, 50:80] = True
    walls[109, 60:70] = False  # a 1 m door is closed by the gap closing
    assert derive_valid_space(walls, GazeboConfig())[60, 60]


def authors_raster(directory: Path) -> tuple[np.ndarray, np.ndarray]:
    """The authors' walls and valid space at 0.1 m, cut to even sizes first: the loader pads
    an odd last row or column with wall, which is its edge rule, not the authors' plan."""
    occupancy = np.load(directory / "occ_map.npy")
    labels = np.load(directory / "valid_space.npy")
    rows, cols = (s - s % 2 for s in occupancy.shape)

    def blocks(a: np.ndarray) -> np.ndarray:
        return a[:rows, :cols].reshape(rows // 2, 2, cols // 2, 2).any(axis=(1, 3))

    return blocks(occupancy == 0), blocks(labels > 0)


def aligned(ours: np.ndarray, theirs: np.ndarray, search: int = 8) -> tuple[int, int]:
    """The shift (rows, cols) of our raster onto theirs with the most wall cells in common:
    the two rasters' origins are unrelated (theirs starts at the plan, ours at a margin)."""

    def overlap(dr: int, dc: int) -> int:
        return int((shifted(ours, theirs.shape, dr, dc) & theirs).sum())

    return max(((dr, dc) for dr in range(-search, search + 1) for dc in range(-search, search + 1)),
               key=lambda shift: overlap(*shift))  # fmt: skip


def shifted(array: np.ndarray, shape: tuple[int, int], dr: int, dc: int) -> np.ndarray:
    """`array` moved by (dr, dc) onto a grid of `shape` (cells moved off it are lost)."""
    out = np.zeros(shape, dtype=array.dtype)
    rows = slice(max(dr, 0), min(dr + array.shape[0], shape[0]))
    cols = slice(max(dc, 0), min(dc + array.shape[1], shape[1]))
    out[rows, cols] = array[rows.start - dr : rows.stop - dr, cols.start - dc : cols.stop - dc]
    return out


def agreement(floor: str, kth_dev_dir: Path) -> tuple[float, float, float]:
    """(share of their wall cells within one cell of ours, share of ours within one cell of
    theirs, valid-space IoU) for a check floor."""
    ours = load_world(f"kth-sdf:{floor}")
    walls, valid = authors_raster(kth_dev_dir / floor)
    dr, dc = aligned(ours.occupancy, walls)
    our_walls = shifted(ours.occupancy, walls.shape, dr, dc)
    our_valid = shifted(ours.valid_space, walls.shape, dr, dc)
    near_ours = ndimage.distance_transform_cdt(~our_walls, "chessboard") <= 1
    near_theirs = ndimage.distance_transform_cdt(~walls, "chessboard") <= 1
    iou = (our_valid & valid).sum() / (our_valid | valid).sum()
    return float(near_ours[walls].mean()), float(near_theirs[our_walls].mean()), float(iou)


@NEEDS_KTH_SDF
@pytest.mark.parametrize("floor", KTH_VALIDATION_MAPS)
def test_check_floors_agree_with_the_authors_rasters(floor, kth_dev_dir) -> None:
    theirs_near_ours, ours_near_theirs, valid_iou = agreement(floor, kth_dev_dir)
    assert theirs_near_ours >= 0.95 and ours_near_theirs >= 0.95
    assert valid_iou >= 0.90


def test_a_gazebo_world_renders_to_a_png_from_the_command_line(tmp_path, capsys) -> None:
    from mapex.worlds.__main__ import main

    path = write(tmp_path / "room.world", world(model("m", "0 0 0 0 0 0", room_links(6, 4))))
    assert main(["--world", str(path), "--out", str(tmp_path / "room.png")]) == 0
    assert (tmp_path / "room.png").stat().st_size > 0
    assert "room: " in capsys.readouterr().out
    assert main(["--world", str(tmp_path / "none.world")]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "No such file" in error[0]
    assert main(["--list", "kth-validation"]) == 0
    assert len(capsys.readouterr().out.split()) == 18
