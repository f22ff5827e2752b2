"""Small hand-made worlds for the goal-rule tests: a door seen at a grazing angle, a room
sealed but for a slit too narrow to drive through."""

import numpy as np

from mapex.worlds.base import World

ROOM_CENTRE = (80, 30)


def grazing_door_world() -> World:
    """A closed room (rows 60-99, cols 10-49) whose only door (cols 12-15) goes through a
    4-cell-thick wall into a corridor, with a hall beyond it.

    From the room centre `ROOM_CENTRE` the door is seen at a grazing angle: the first scan
    shows the corridor only as a narrow diagonal sliver of free cells that no path without
    corner cutting can follow, so the frontier point of that cluster is out of reach.
    """
    occupancy = np.ones((120, 140), dtype=bool)
    occupancy[60:100, 10:50] = False  # the room
    occupancy[56:60, 12:16] = False  # its door through the thick wall
    occupancy[40:56, 5:135] = False  # the corridor
    occupancy[36:40, 60:70] = False  # a door into the hall
    occupancy[5:36, 5:135] = False  # the hall
    return World("grazing-door", occupancy, ~occupancy)


def slit_room_world() -> World:
    """The same building, but the room's door is a 2-cell slit: the robot sees through it and
    can never pass (walls are inflated by one cell), so frontiers stay out of reach. The
    valid space is the room alone, so the room is the largest part of the building and a
    start there is allowed (a start cut off from the largest part is refused)."""
    occupancy = grazing_door_world().occupancy.copy()
    occupancy[56:60, 12:16] = True
    occupancy[56:60, 29:31] = False  # the slit, facing the room centre
    valid = np.zeros_like(occupancy)
    valid[60:100, 10:50] = True
    return World("slit-room", occupancy, valid)
