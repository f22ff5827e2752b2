"""Settings of the procedural office floor plans (`mapex.worlds.procedural`)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ProceduralConfig:
    """Procedural office floor plans (docs/algorithms.md#worlds, mapex.worlds.procedural); sizes
    in 0.1 m cells.

    "Depth" is a room's size across its row of rooms, "width" its size along the corridor.
    """

    min_rows: int = 150  # map size
    max_rows: int = 400
    min_cols: int = 250
    max_cols: int = 700
    min_margin_cells: int = 2  # solid wall between the building and the map border
    max_margin_cells: int = 10
    transposed_probability: float = 0.25  # main corridors run along the rows, not the columns
    corridor_width_min: int = 15  # 1.5 m
    corridor_width_max: int = 25  # 2.5 m
    max_parallel_corridors: int = 6
    room_depth_min: int = 30  # 3 m
    room_depth_max: int = 80  # 8 m
    room_depth_jitter: float = 0.2  # relative spread of the depths of a building's room rows
    room_width_min: int = 25  # narrowest room along its corridor
    room_width_max: int = 90
    room_module_min: int = 30  # repeated room width of one row of rooms
    room_module_max: int = 55
    double_room_probability: float = 0.2  # a room two modules wide
    extra_corridor_odds: float = 0.5  # relative odds of each further parallel corridor
    segment_length_min: int = 60  # room-row length between cross corridors
    cross_corridor_spacing_min: int = 150  # typical distance between cross corridors
    cross_corridor_spacing_max: int = 300
    segment_jitter: float = 0.4  # relative spread of the segment lengths
    end_cross_corridor_probability: float = 0.25  # a cross corridor at one end of the building
    cross_extension_probability: float = 0.3  # a cross corridor runs on to the outer wall
    end_room_probability: float = 0.3  # per corridor end: a room closes the corridor
    end_room_length_min: int = 30
    end_room_length_max: int = 60
    hall_count_min: int = 1  # large rooms per building (capped by blocks_per_hall_min)
    hall_count_max: int = 3
    blocks_per_hall_min: int = 3  # small buildings get fewer halls (none below 3 blocks)
    hall_length_min: int = 60
    hall_length_max: int = 200
    merged_hall_probability: float = 0.5  # a hall spans two back-to-back room rows
    suite_probability: float = 0.25  # an outer room row split into front and inner rooms
    suite_room_depth_min: int = 28
    suite_front_fraction_min: float = 0.45  # share of the depth taken by the front rooms
    suite_front_fraction_max: float = 0.6
    lobby_probability: float = 0.4  # one room left open to its corridor (an open area)
    extra_door_probability: float = 0.15  # per room: a connecting door to a neighbouring room
    door_width_min: int = 8  # 0.8 m
    door_width_max: int = 12  # 1.2 m
    door_offset_max: int = 6  # door distance from the room corner (shared along a row)
    wall_thickness_min: int = 2  # interior walls, one thickness per plan
    wall_thickness_max: int = 3
    # The outline's walls (between the building and the outside); None: as thick as the
    # interior walls of the same plan.
    outer_wall_thickness: int | None = None
    outline_rectangle_weight: float = 0.3  # relative odds of the building outlines
    outline_l_weight: float = 0.2
    outline_t_weight: float = 0.15
    outline_u_weight: float = 0.15
    outline_courtyard_weight: float = 0.2
    max_cutout_fraction: float = 0.4  # most of the building rectangle an outline may cut away
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
class HouseExpoConfig:
    """Office-sized worlds made of HouseExpo houses along a corridor
    (`houseexpo-corridor:<seed>`, mapex.worlds.houseexpo); sizes in 0.1 m cells."""

    houses_per_world: int = 6  # half above the corridor, half below
    max_house_side_cells: int = 220  # larger plans are passed over
    min_house_side_cells: int = 40
    corridor_width_cells: int = 20  # 2 m
    door_width_cells: int = 10  # 1 m, cut through a house's outer wall to the corridor
    max_door_depth_cells: int = 6  # thickest outer wall a door may be cut through
    margin_cells: int = 2  # solid wall between the houses and the map border
    max_draws: int = 200  # plans drawn per world before giving up
