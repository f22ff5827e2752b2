"""Where a team starts: by default deployed together, about `team.spacing_cells` apart.

Robot 0 takes the chosen start (a corner 0-3 or a cell); each next robot takes the eligible
start cell (free, in valid space, clear of walls) of the same connected free space that is
nearest to robot 0 and at least `spacing_cells` from every robot placed before it; ties go
to the earliest cell in row-major order. Explicit cells, one per robot, are taken as given
(robots are points and may share a cell).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from mapex.config import ExplorationConfig
from mapex.grid import Cell
from mapex.worlds import StartSpec, World, WorldError, start_cell
from mapex.worlds.starts import eligible_start_cells, start_cells


def team_start_cells(
    world: World, starts: Sequence[StartSpec], robots: int, config: ExplorationConfig
) -> list[Cell]:
    """The start cell of each of `robots` robots; WorldError (one line) when they do not fit.

    `starts`: one start (the team deploys around it) or one start per robot.
    """
    clearance = config.world.start_clearance_cells
    if len(starts) == robots and robots > 1:
        return start_cells(world, starts, clearance)  # all judged at once
    if len(starts) != 1:
        raise WorldError(f"{len(starts)} starts given for {robots} robots (give 1 or {robots})")
    first = start_cell(world, starts[0], clearance)
    return deploy_around(world, first, robots, config.team.spacing_cells, clearance)


def deploy_around(
    world: World, first: Cell, robots: int, spacing_cells: int, clearance_cells: int
) -> list[Cell]:
    """`first`, then `robots - 1` eligible cells near it, `spacing_cells` apart (module doc)."""
    if robots == 1:
        return [first]
    eligible = eligible_start_cells(world, clearance_cells)
    labels, _ = ndimage.label(~world.occupancy & world.valid_space)
    rows, cols = np.nonzero(eligible & (labels == labels[first]))
    order = np.argsort((rows - first[0]) ** 2 + (cols - first[1]) ** 2, kind="stable")
    candidates = np.stack([rows[order], cols[order]], axis=1)
    placed = [first]
    for cell in candidates:
        if len(placed) == robots:
            break
        gaps = np.hypot(*(np.asarray(placed) - cell).T)
        if gaps.min() >= spacing_cells:
            placed.append((int(cell[0]), int(cell[1])))
    if len(placed) < robots:
        raise WorldError(
            f"world '{world.name}': room for {len(placed)} robots {spacing_cells} cells apart "
            f"around {first}, not {robots} (--set team.spacing_cells=N, or give every start)"
        )
    return placed
