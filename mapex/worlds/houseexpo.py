"""HouseExpo house plans as worlds (docs/algorithms.md#worlds).

`plans.npz` holds ~33,700 house plans as one polygon ring each, in metres, around the free
space (interior walls are notches cut into the ring). A plan is rasterised at 0.1 m by the
data's own rule: a cell is free iff all 100 of its 1 cm sub-cell centres lie inside the
ring (even-odd test), so 11-12 cm interior walls survive as 2-3 cell walls and no two free
cells touch diagonally through a wall. Row <-> y, column <-> x, as in HouseExpo's images.

Two kinds of world: `houseexpo:<index>` (one house, plan number `index`) and
`houseexpo-corridor:<seed>` (several houses drawn with `seed`, each joined by a 1 m door
to a 2 m corridor between them: an office-sized world of house-sized rooms).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy import ndimage

from mapex.io_limits import check_npz
from mapex.worlds.base import (
    CORRIDOR_PREFIX,
    HOUSE_PREFIX,
    World,
    WorldError,
    one_line,
    parse_seed,
)
from mapex.worlds.config import HouseExpoConfig
from mapex.worlds.data import HOUSEEXPO_PLANS

CELL_CM = 10  # 0.1 m cells
SUB_CM = 1  # the data's precision: vertices lie on a 1 cm grid
PLAN_KEYS = ("ids", "offsets", "verts")


@dataclass(frozen=True)
class HousePlans:
    """Polygon rings: plan i's vertices (x, y metres) are verts[offsets[i]:offsets[i + 1]]."""

    ids: np.ndarray
    offsets: np.ndarray
    verts: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def ring(self, index: int) -> np.ndarray:
        """Plan `index`'s ring, (n, 2) float metres; a one-line WorldError if out of range."""
        if not 0 <= index < len(self):
            raise WorldError(
                f"no HouseExpo plan {index}: there are {len(self)} (0-{len(self) - 1})"
            )
        return self.verts[self.offsets[index] : self.offsets[index + 1]]


@lru_cache(maxsize=2)
def load_plans(path: Path = HOUSEEXPO_PLANS) -> HousePlans:
    """The plans in `path` (HouseExpo's plans.npz); a one-line WorldError naming a bad file
    (its members' headers are checked against the file and `max_plans_bytes` first)."""
    path = Path(path)
    if not path.exists():
        raise WorldError(f"missing HouseExpo plans file: {path}")
    hint = "HouseExpoConfig.max_plans_bytes"
    try:
        check_npz(path, HouseExpoConfig().max_plans_bytes, "plans", hint)
    except (ValueError, OSError) as error:
        raise WorldError(one_line(error)) from None
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in PLAN_KEYS if key in archive.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as error:
        raise WorldError(f"not a loadable .npz file: {path} ({one_line(error)})") from None
    missing = [key for key in PLAN_KEYS if key not in arrays]
    if missing:
        raise WorldError(f"{path}: no {', '.join(missing)} array (expected {PLAN_KEYS})")
    plans = HousePlans(*(arrays[key] for key in PLAN_KEYS))
    _check_plans(plans, path)
    return plans


def _check_plans(plans: HousePlans, path: Path) -> None:
    offsets = plans.offsets
    if plans.verts.ndim != 2 or plans.verts.shape[1] != 2:
        raise WorldError(f"{path}: verts of shape {plans.verts.shape}, expected (M, 2)")
    if offsets.ndim != 1 or len(offsets) != len(plans.ids) + 1:
        raise WorldError(f"{path}: {len(offsets)} offsets for {len(plans.ids)} plans")
    if offsets[0] != 0 or offsets[-1] != len(plans.verts) or np.any(np.diff(offsets) < 3):
        raise WorldError(f"{path}: offsets do not split verts into rings of 3 or more vertices")


def rasterise_plan(ring_m: np.ndarray) -> np.ndarray:
    """Free cells (bool (rows, cols), row <-> y) of one plan at 0.1 m: a cell is free iff all
    its 1 cm sub-cell centres are inside the ring (even-odd rule). Row 0, column 0 and the
    last row and column are always wall, so the plan is sealed."""
    points = np.rint(np.asarray(ring_m, np.float64) * 100).astype(np.int64)
    if points.min() < 0:
        raise WorldError("a HouseExpo ring with negative coordinates")
    k = CELL_CM // SUB_CM
    rows = -(-points[:, 1].max() // CELL_CM) + 1
    cols = -(-points[:, 0].max() // CELL_CM) + 1
    inside = _even_odd_fill(points.astype(np.float64), rows * k, cols * k)
    return inside.reshape(rows, k, cols, k).all(axis=(1, 3))


def _even_odd_fill(a: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Sub-cells (bool (rows, cols), 1 unit each) whose centres are inside the ring `a`: each
    edge toggles the first centre at or right of where it crosses the centre's row; a running
    parity along the row then marks the inside."""
    b = np.roll(a, -1, axis=0)
    low, high = np.minimum(a[:, 1], b[:, 1]), np.maximum(a[:, 1], b[:, 1])
    first = np.ceil(low - 0.5).astype(np.int64)
    count = np.maximum(np.ceil(high - 0.5).astype(np.int64) - first, 0)
    edge = np.repeat(np.arange(len(a)), count)
    row = (
        np.repeat(first, count)
        + np.arange(count.sum())
        - np.repeat(np.cumsum(count) - count, count)
    )
    y = row + 0.5
    x = a[edge, 0] + (y - a[edge, 1]) * (b[edge, 0] - a[edge, 0]) / (b[edge, 1] - a[edge, 1])
    col = np.clip(np.ceil(x - 0.5).astype(np.int64), 0, cols)
    toggles = np.zeros((rows, cols + 1), np.uint8)
    np.add.at(toggles, (row, col), 1)
    return (np.cumsum(toggles, axis=1, dtype=np.uint8)[:, :cols] & 1).astype(bool)


def house_world(index: int, plans: HousePlans | None = None) -> World:
    """One house as a world: its free cells are the valid space, everything else wall."""
    free = rasterise_plan((plans or load_plans()).ring(index))
    return World(f"{HOUSE_PREFIX}{index}", ~free, free.copy())


def house_world_of_spec(index: str) -> World:
    """The world of spec `houseexpo:<index>` (`index` as written after the prefix)."""
    return house_world(parse_seed(index, "HouseExpo plan index"))


def corridor_world_of_spec(seed: str) -> World:
    """The world of spec `houseexpo-corridor:<seed>`."""
    return corridor_world(parse_seed(seed))


def corridor_world(
    seed: int, config: HouseExpoConfig | None = None, plans: HousePlans | None = None
) -> World:
    """Houses drawn with `seed` above and below a straight corridor, each with a door to it.

    Valid space: the free cells connected to the corridor (a room with no opening in the
    data stays free but outside it)."""
    plans, config = plans or load_plans(), config or HouseExpoConfig()
    houses = _draw_houses(np.random.default_rng(seed), plans, config)
    top, bottom = houses[: (len(houses) + 1) // 2], houses[(len(houses) + 1) // 2 :]
    bottom = [np.flipud(house) for house in bottom]  # doors face up, towards the corridor
    margin, corridor = config.margin_cells, config.corridor_width_cells
    top_rows = max(h.shape[0] for h in top)
    bottom_rows = max((h.shape[0] for h in bottom), default=0)
    width = max(sum(h.shape[1] for h in top), sum(h.shape[1] for h in bottom))
    free = np.zeros((top_rows + corridor + bottom_rows + 2 * margin, width + 2 * margin), bool)
    corridor_top = margin + top_rows
    free[corridor_top : corridor_top + corridor, margin : margin + width] = True
    _place_row(free, top, corridor_top, margin, above=True)
    _place_row(free, bottom, corridor_top + corridor, margin, above=False)
    labels, _ = ndimage.label(free)
    valid = labels == labels[corridor_top, margin]
    return World(f"{CORRIDOR_PREFIX}{seed}", ~free, valid)


def _place_row(
    free: np.ndarray, houses: list[np.ndarray], edge: int, left: int, above: bool
) -> None:
    """Paste houses side by side, their bottom (above) or top (below) on row `edge`."""
    for house in houses:
        rows, cols = house.shape
        top = edge - rows if above else edge
        free[top : top + rows, left : left + cols] |= house
        left += cols


def _draw_houses(
    rng: np.random.Generator, plans: HousePlans, config: HouseExpoConfig
) -> list[np.ndarray]:
    """`houses_per_world` house rasters, each turned so that a door to the corridor can be
    cut through its bottom wall, and cut."""
    houses: list[np.ndarray] = []
    for _ in range(config.max_draws):
        if len(houses) == config.houses_per_world:
            return houses
        index = int(rng.integers(len(plans)))
        ring = plans.ring(index)
        sides_cells = np.ptp(ring, axis=0) * 100 / CELL_CM
        if (
            not config.min_house_side_cells
            <= sides_cells.min()
            <= sides_cells.max()
            <= config.max_house_side_cells
        ):
            continue
        house = _with_door(rasterise_plan(ring), config, int(rng.integers(4)))
        if house is not None:
            houses.append(house)
    raise WorldError(
        f"could not draw {config.houses_per_world} HouseExpo houses in {config.max_draws} draws"
    )


def _with_door(free: np.ndarray, config: HouseExpoConfig, first_turn: int) -> np.ndarray | None:
    """The house turned (trying quarter turns from `first_turn`) so that its bottom wall is
    thinnest where a door fits, with the door cut; None if no side has such a place."""
    width = config.door_width_cells
    for turn in range(first_turn, first_turn + 4):
        house = np.rot90(free, turn)
        rows = house.shape[0]
        has_free = house.any(axis=0)
        last_free = rows - 1 - np.argmax(house[::-1], axis=0)
        depth = np.where(has_free, rows - 1 - last_free, rows)  # wall cells below the last free one
        if len(depth) < width:
            continue
        window_depth = np.lib.stride_tricks.sliding_window_view(depth, width).max(axis=1)
        best = int(np.argmin(window_depth))
        if window_depth[best] > config.max_door_depth_cells:
            continue
        house = house.copy()
        for col in range(best, best + width):
            house[last_free[col] :, col] = True
        return house
    return None
