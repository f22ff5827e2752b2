"""Settings of the procedural office floor plans (`mapex.worlds.procedural`)."""

from __future__ import annotations

from dataclasses import dataclass

from mapex.config import Checked, ranged, share

MAX_PLAN_SIDE_CELLS = 10_000  # 1 km: a procedural plan's rows and columns at most


@dataclass(frozen=True)
class ProceduralConfig(Checked):
    """Procedural office floor plans (docs/algorithms.md#worlds, mapex.worlds.procedural); sizes
    in 0.1 m cells.

    "Depth" is a room's size across its row of rooms, "width" its size along the corridor.
    """

    min_rows: int = ranged(150, 1, MAX_PLAN_SIDE_CELLS)  # map size
    max_rows: int = ranged(400, 1, MAX_PLAN_SIDE_CELLS)
    min_cols: int = ranged(250, 1, MAX_PLAN_SIDE_CELLS)
    max_cols: int = ranged(700, 1, MAX_PLAN_SIDE_CELLS)
    min_margin_cells: int = ranged(2, 0)  # solid wall between the building and the map border
    max_margin_cells: int = ranged(10, 0)
    # main corridors run along the rows, not the columns
    transposed_probability: float = share(0.25)
    corridor_width_min: int = ranged(15, 1)  # 1.5 m
    corridor_width_max: int = ranged(25, 1)  # 2.5 m
    max_parallel_corridors: int = ranged(6, 1)
    room_depth_min: int = ranged(30, 1)  # 3 m
    room_depth_max: int = ranged(80, 1)  # 8 m
    room_depth_jitter: float = share(0.2)  # relative spread of the depths of a building's room rows
    room_width_min: int = ranged(25, 1)  # narrowest room along its corridor
    room_width_max: int = ranged(90, 1)
    room_module_min: int = ranged(30, 1)  # repeated room width of one row of rooms
    room_module_max: int = ranged(55, 1)
    double_room_probability: float = share(0.2)  # a room two modules wide
    extra_corridor_odds: float = ranged(0.5, 0)  # relative odds of each further parallel corridor
    segment_length_min: int = ranged(60, 1)  # room-row length between cross corridors
    cross_corridor_spacing_min: int = ranged(150, 1)  # typical distance between cross corridors
    cross_corridor_spacing_max: int = ranged(300, 1)
    segment_jitter: float = share(0.4)  # relative spread of the segment lengths
    # a cross corridor at one end of the building
    end_cross_corridor_probability: float = share(0.25)
    cross_extension_probability: float = share(0.3)  # a cross corridor runs on to the outer wall
    end_room_probability: float = share(0.3)  # per corridor end: a room closes the corridor
    end_room_length_min: int = ranged(30, 1)
    end_room_length_max: int = ranged(60, 1)
    hall_count_min: int = ranged(1, 0)  # large rooms per building (capped by blocks_per_hall_min)
    hall_count_max: int = ranged(3, 0)
    blocks_per_hall_min: int = ranged(3, 1)  # small buildings get fewer halls (none below 3 blocks)
    hall_length_min: int = ranged(60, 1)
    hall_length_max: int = ranged(200, 1)
    merged_hall_probability: float = share(0.5)  # a hall spans two back-to-back room rows
    suite_probability: float = share(0.25)  # an outer room row split into front and inner rooms
    suite_room_depth_min: int = ranged(28, 1)
    suite_front_fraction_min: float = share(0.45)  # share of the depth taken by the front rooms
    suite_front_fraction_max: float = share(0.6)
    lobby_probability: float = share(0.4)  # one room left open to its corridor (an open area)
    # per room: a connecting door to a neighbouring room
    extra_door_probability: float = share(0.15)
    door_width_min: int = ranged(8, 1)  # 0.8 m
    door_width_max: int = ranged(12, 1)  # 1.2 m
    door_offset_max: int = ranged(6, 0)  # door distance from the room corner (shared along a row)
    wall_thickness_min: int = ranged(2, 1)  # interior walls, one thickness per plan
    wall_thickness_max: int = ranged(3, 1)
    # The outline's walls (between the building and the outside); None: as thick as the
    # interior walls of the same plan.
    outer_wall_thickness: int | None = ranged(None, 1)
    outline_rectangle_weight: float = ranged(0.3, 0)  # relative odds of the building outlines
    outline_l_weight: float = ranged(0.2, 0)
    outline_t_weight: float = ranged(0.15, 0)
    outline_u_weight: float = ranged(0.15, 0)
    outline_courtyard_weight: float = ranged(0.2, 0)
    # most of the building rectangle an outline may cut away
    max_cutout_fraction: float = share(0.4)
    # Free space around the building and in its cut-away parts (as in the KTH maps),
    # instead of solid wall; its worlds are named "generated-open:<seed>".
    free_outside: bool = False


# The plans with free space outside (generated-open:SEED), which the predictor trains on,
# take their walls from the KTH training maps 50015847 and 50015848: between two rooms
# mostly 4 cells thick (3 in about a fifth of them), around the building 2 cells thick
# (93 % of their outline).
OPEN_PLAN_CONFIG = ProceduralConfig(
    wall_thickness_min=3, wall_thickness_max=4, outer_wall_thickness=2, free_outside=True
)


@dataclass(frozen=True)
class HouseExpoConfig(Checked):
    """Office-sized worlds made of HouseExpo houses along a corridor
    (`houseexpo-corridor:<seed>`, mapex.worlds.houseexpo); sizes in 0.1 m cells."""

    houses_per_world: int = ranged(6, 1)  # half above the corridor, half below
    max_house_side_cells: int = ranged(220, 1)  # larger plans are passed over
    min_house_side_cells: int = ranged(40, 1)
    corridor_width_cells: int = ranged(20, 1)  # 2 m
    door_width_cells: int = ranged(10, 1)  # 1 m, cut through a house's outer wall to the corridor
    max_door_depth_cells: int = ranged(6, 0)  # thickest outer wall a door may be cut through
    margin_cells: int = ranged(2, 0)  # solid wall between the houses and the map border
    max_draws: int = ranged(200, 1)  # plans drawn per world before giving up
    # plans.npz unpacks to about 53 MB; a larger file (or one whose headers claim more) is refused
    max_plans_bytes: int = ranged(256 * 2**20, 1)


@dataclass(frozen=True)
class GazeboConfig(Checked):
    """Gazebo SDF worlds rasterised into floor plans (`FILE.world`, mapex.worlds.gazebo);
    lengths in metres unless the name says cells."""

    # a geometry is a wall when its vertical extent holds the 2D LiDAR's scan plane
    scan_height_m: float = ranged(0.3, 0)
    margin_cells: int = ranged(2, 0)  # free cells between the outermost wall and the border
    # Gaps in the walls up to twice this wide (doors, windows) are closed when the building's
    # inside is derived; 1.2 m closes the KTH floors' windows and keeps their courtyards out
    # (valid-space IoU 0.946 / 0.913 against the authors' rasters of the two check floors).
    gap_closing_cells: int = ranged(12, 1)
    # inside regions smaller than this (0.5 m^2: gaps between doubled walls) are not rooms
    min_room_cells: int = ranged(50, 1)
    # the walls of the rooms are valid space up to this many cells from a room (the KTH
    # rasters' rooms reach into their walls by about one 0.1 m cell)
    valid_wall_cells: int = ranged(1, 0)
    # an enclosing frame side (frame=drop): within this of a side of the walls' bounding box
    frame_tolerance_m: float = ranged(0.3, 0)
    max_geometries: int = ranged(200_000, 1)  # larger worlds are refused before rasterising
