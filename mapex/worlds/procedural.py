"""Seeded office-style floor plans in the KTH world representation (docs/algorithms.md#worlds).

They are the embedded default world and the predictor's main training data, so they copy
the structure of real office plans: bands of room rows and corridors joined by cross
corridors, cut into L, T, U and courtyard outlines, rooms of a repeated module width, doors
along a spanning tree, sealed or with free space outside; how a plan is built is in
docs/algorithms.md#worlds.

Run `python -m mapex.worlds --seed 3 --out plan.png` (mapex/worlds/__main__.py; add
`--free-outside` for the open plan) to look at one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from mapex.worlds.base import World, WorldError, generated_prefix, parse_seed
from mapex.worlds.config import OPEN_PLAN_CONFIG, ProceduralConfig

CORRIDOR_LABEL = 1  # corridors and open areas share one label: no walls between them
FIRST_ROOM_LABEL = 2
EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)
OUTLINES = ("rectangle", "L", "T", "U", "courtyard")
DEFAULT_CONFIG = ProceduralConfig()


class Rect(NamedTuple):
    """Half-open cell rectangle [y0, y1) x [x0, x1)."""

    y0: int
    y1: int
    x0: int
    x1: int


class Edge(NamedTuple):
    """A wall shared by space `a` and space `b`; `side` is where b lies seen from a.

    `coord` is the boundary line (b's first row/col for "bottom"/"right"), [lo, hi) its
    extent along the wall.
    """

    a: int
    b: int
    side: str
    coord: int
    lo: int
    hi: int


@dataclass
class _Band:
    kind: str  # "room" or "corridor"
    y0: int
    y1: int
    corridor_sides: tuple[str, ...] = ()  # "top" / "bottom" neighbours that are corridors
    partner: int | None = None  # index of the back-to-back room band


@dataclass
class _Space:
    rect: Rect
    is_root: bool  # corridor or open area, reachable by construction
    door_side: str = "top"  # preferred side of its main door
    anchor: str = "centre"  # where its doors sit along a wall: "low", "high" or "centre"
    offset: int = 0  # door distance from the anchored corner
    door_width: int = 10
    is_hall: bool = False


@dataclass(frozen=True)
class FloorLayout:
    """A generated world with its room structure.

    labels: int32 map, 0 outside the building, CORRIDOR_LABEL for corridors and open
    areas, FIRST_ROOM_LABEL.. one per room (walls carry the label of a space they bound).
    doors: bool map of the door openings (cells that are walls when the doors are shut).
    """

    world: World
    labels: np.ndarray
    doors: np.ndarray


def generate_floor_plan(seed: int, config: ProceduralConfig = DEFAULT_CONFIG) -> World:
    """The office floor plan of `seed` (deterministic), named "generated:<seed>", or
    "generated-open:<seed>" with `config.free_outside`."""
    return generate_layout(seed, config).world


def generated_world(seed: str) -> World:
    """The world of spec `generated:<seed>` (`seed` as written after the prefix)."""
    return generate_floor_plan(parse_seed(seed), plan_config(free_outside=False))


def open_generated_world(seed: str) -> World:
    """The world of spec `generated-open:<seed>`: the same plan with free space outside."""
    return generate_floor_plan(parse_seed(seed), plan_config(free_outside=True))


def plan_config(free_outside: bool) -> ProceduralConfig:
    """The default (sealed) plan configuration, or that of the plans with free space outside
    the building and KTH-like walls (`OPEN_PLAN_CONFIG`)."""
    return OPEN_PLAN_CONFIG if free_outside else DEFAULT_CONFIG


def generate_layout(seed: int, config: ProceduralConfig = DEFAULT_CONFIG) -> FloorLayout:
    """The floor plan of `seed` with its labels and doors; see the module docstring."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise WorldError(f"bad generated seed {seed!r}: expected a non-negative integer")
    rng = np.random.default_rng(int(seed))
    rows, cols, margin, transposed = _sample_frame(rng, config)
    stack_len, long_len = (cols, rows) if transposed else (rows, cols)
    stack_len, long_len = stack_len - 2 * margin, long_len - 2 * margin
    wall_cells = int(rng.integers(config.wall_thickness_min, config.wall_thickness_max + 1))

    bands = _sample_bands(rng, stack_len, config)
    crossings = _sample_cross_corridors(rng, stack_len, long_len, bands, config)
    cutouts = _sample_cutouts(rng, long_len, bands, crossings, config)
    spaces = _corridor_spaces(rng, long_len, bands, crossings, config)
    spaces += _room_spaces(rng, long_len, bands, crossings, cutouts, config)
    spaces = [s for s in spaces if not any(_contains(c, s.rect) for c in cutouts)]
    spaces = [replace(s, rect=_shift(s.rect, margin)) for s in spaces]
    cutouts = [_shift(c, margin) for c in cutouts]

    edges = _shared_edges([s.rect for s in spaces], config.door_width_min + 2 * (wall_cells + 1))
    _open_lobby(rng, spaces, edges, config)
    labels = _paint_labels(spaces, cutouts, (stack_len + 2 * margin, long_len + 2 * margin))
    outside = labels == 0
    outer_cells = config.outer_wall_thickness or wall_cells
    walls = _walls_from_labels(labels, wall_cells, outer_cells, not config.free_outside)
    doors = _door_mask(rng, spaces, edges, wall_cells, labels.shape, config) & ~outside
    occupancy = np.where(outside, walls, _seal_unreachable(walls & ~doors | outside))

    flips = (transposed, bool(rng.random() < 0.5), bool(rng.random() < 0.5))
    occupancy, labels, doors = (_orient(a, *flips) for a in (occupancy, labels, doors))
    name = f"{generated_prefix(config.free_outside)}{seed}"
    world = World(name, occupancy, (labels > 0) & ~occupancy)
    return FloorLayout(world, labels, doors & ~occupancy)


# ---------------------------------------------------------------- frame and bands


def _sample_frame(rng: np.random.Generator, cfg: ProceduralConfig) -> tuple[int, int, int, bool]:
    """Map rows, cols, the outside margin and whether the bands run along the rows."""
    rows = int(rng.integers(cfg.min_rows, cfg.max_rows + 1))
    cols = int(rng.integers(cfg.min_cols, cfg.max_cols + 1))
    margin = int(rng.integers(cfg.min_margin_cells, cfg.max_margin_cells + 1))
    return rows, cols, margin, bool(rng.random() < cfg.transposed_probability)


def _sample_bands(rng: np.random.Generator, stack_len: int, cfg: ProceduralConfig) -> list[_Band]:
    """The stack of room rows and corridors filling `stack_len` cells, top to bottom."""
    n_corridors, n_doubled = _pick_stack_shape(rng, stack_len, cfg)
    doubled = set(rng.choice(n_corridors - 1, size=n_doubled, replace=False).tolist())
    kinds = ["room"]
    for gap in range(n_corridors - 1):
        kinds += ["corridor"] + ["room"] * (2 if gap in doubled else 1)
    kinds += ["corridor", "room"]
    widths = _band_widths(rng, kinds, stack_len, cfg)
    ends = np.cumsum(widths)
    bands = [_Band(k, int(e - w), int(e)) for k, w, e in zip(kinds, widths, ends, strict=True)]
    for i, band in enumerate(bands):
        if band.kind != "room":
            continue
        above, below = bands[i - 1] if i else None, bands[i + 1] if i + 1 < len(bands) else None
        band.corridor_sides = tuple(
            side
            for side, other in (("top", above), ("bottom", below))
            if other is not None and other.kind == "corridor"
        )
        if below is not None and below.kind == "room":
            band.partner, below.partner = i + 1, i
    return bands


def _pick_stack_shape(
    rng: np.random.Generator, stack_len: int, cfg: ProceduralConfig
) -> tuple[int, int]:
    """Number of parallel corridors and of back-to-back room-row pairs that fit."""
    mean_corridor = (cfg.corridor_width_min + cfg.corridor_width_max) / 2
    low = cfg.room_depth_min * (1 + cfg.room_depth_jitter / 2)
    high = cfg.room_depth_max * (1 - cfg.room_depth_jitter / 2)
    options = [
        (n, d)
        for n in range(1, cfg.max_parallel_corridors + 1)
        for d in range(n)
        if low <= (stack_len - n * mean_corridor) / (n + 1 + d) <= high
    ]
    if not options:
        raise WorldError(f"no office layout fits {stack_len} cells with this ProceduralConfig")
    weights = np.array([cfg.extra_corridor_odds ** (n - 1) for n, _ in options])
    return options[int(rng.choice(len(options), p=weights / weights.sum()))]


def _band_widths(
    rng: np.random.Generator, kinds: list[str], stack_len: int, cfg: ProceduralConfig
) -> list[int]:
    """Corridor widths at random, room depths jittered to fill the rest exactly."""
    n_corridors = kinds.count("corridor")
    corridors = rng.integers(cfg.corridor_width_min, cfg.corridor_width_max + 1, n_corridors)
    room_total = stack_len - int(corridors.sum())
    n_rooms = len(kinds) - n_corridors
    depths = _split_exact(room_total, np.ones(n_rooms))
    for _ in range(20):
        jitter = cfg.room_depth_jitter
        trial = _split_exact(room_total, rng.uniform(1 - jitter, 1 + jitter, n_rooms))
        if cfg.room_depth_min <= min(trial) and max(trial) <= cfg.room_depth_max:
            depths = trial
            break
    corridor_iter, depth_iter = iter(corridors.tolist()), iter(depths)
    return [next(corridor_iter) if k == "corridor" else next(depth_iter) for k in kinds]


def _split_exact(total: int, weights: np.ndarray) -> list[int]:
    """Integers proportional to `weights` that sum to `total`."""
    edges = np.round(np.cumsum(weights) / np.sum(weights) * total).astype(int)
    return np.diff(edges, prepend=0).tolist()


# ---------------------------------------------------------------- cross corridors and outline


def _sample_cross_corridors(
    rng: np.random.Generator,
    stack_len: int,
    long_len: int,
    bands: list[_Band],
    cfg: ProceduralConfig,
) -> list[Rect]:
    """Corridors across the stack, left to right; they join all parallel corridors."""
    corridors = [b for b in bands if b.kind == "corridor"]
    width = int(rng.integers(cfg.corridor_width_min, cfg.corridor_width_max + 1))
    n_min = 1 if len(corridors) > 1 else 0
    n_fit = (long_len - cfg.segment_length_min) // (cfg.segment_length_min + width)
    spacing = rng.uniform(cfg.cross_corridor_spacing_min, cfg.cross_corridor_spacing_max)
    n = int(np.clip(round(long_len / spacing), n_min, max(n_min, n_fit)))
    free = long_len - n * width
    jitter = cfg.segment_jitter
    segments = _split_exact(free, rng.uniform(1 - jitter, 1 + jitter, n + 1))
    if min(segments) < cfg.segment_length_min:
        segments = _split_exact(free, np.ones(n + 1))
    starts = (np.cumsum(segments[:-1]) + width * np.arange(n)).tolist()
    at_end = rng.random() < cfg.end_cross_corridor_probability
    if at_end and segments[0] >= cfg.segment_length_min + width:
        starts.insert(0, 0)
    return [Rect(*_cross_extent(rng, stack_len, corridors, cfg), x, x + width) for x in starts]


def _cross_extent(
    rng: np.random.Generator, stack_len: int, corridors: list[_Band], cfg: ProceduralConfig
) -> tuple[int, int]:
    """Rows of one cross corridor: between the outer parallel corridors, or on to a wall."""
    if len(corridors) == 1:
        reach = str(rng.choice(["up", "down", "both"]))
    elif rng.random() < cfg.cross_extension_probability:
        reach = str(rng.choice(["up", "down"]))
    else:
        reach = "none"
    y0 = 0 if reach in ("up", "both") else corridors[0].y0
    y1 = stack_len if reach in ("down", "both") else corridors[-1].y1
    return y0, y1


def _sample_cutouts(
    rng: np.random.Generator,
    long_len: int,
    bands: list[_Band],
    crossings: list[Rect],
    cfg: ProceduralConfig,
) -> list[Rect]:
    """Parts of the band grid left outside the building (L, T, U, courtyard outlines).

    Outlines are tried in a weighted random order until one fits (a rectangle always
    does). Cuts run along cross corridors, which keep every corridor piece connected,
    or anywhere away from them when only the outer room row goes.
    """
    weights = np.array(
        [
            cfg.outline_rectangle_weight,
            cfg.outline_l_weight,
            cfg.outline_t_weight,
            cfg.outline_u_weight,
            cfg.outline_courtyard_weight,
        ]
    )
    order = rng.choice(len(OUTLINES), size=len(OUTLINES), replace=False, p=weights / weights.sum())
    corridors = [b for b in bands if b.kind == "corridor"]
    k = int(rng.integers(len(corridors)))  # cut the bands above this parallel corridor
    lines = sorted(
        [(c.x0, c.x1) for c in crossings] + _free_cut_lines(rng, long_len, crossings, cfg)
    )
    if k > 0:
        lines = [(a, b) for a, b in lines if a < b]  # deeper cuts follow cross corridors
    area = bands[-1].y1 * long_len
    for outline in (OUTLINES[i] for i in order):
        if outline == "courtyard":
            fits = _courtyard_fits(corridors, crossings, cfg)
        else:
            fits = _side_cut_fits(outline, lines, long_len, corridors[k].y0, cfg)
        fits = [f for f in fits if _area(f) <= cfg.max_cutout_fraction * area]
        if fits:
            return fits[int(rng.integers(len(fits)))]
    return []


def _area(rects: list[Rect]) -> int:
    return sum((r.y1 - r.y0) * (r.x1 - r.x0) for r in rects)


def _courtyard_fits(
    corridors: list[_Band], crossings: list[Rect], cfg: ProceduralConfig
) -> list[list[Rect]]:
    """The room rows between two parallel corridors and two neighbouring cross corridors."""
    return [
        [Rect(upper.y1, lower.y0, left.x1, right.x0)]
        for upper, lower in zip(corridors, corridors[1:], strict=False)
        for left, right in zip(crossings, crossings[1:], strict=False)
        if right.x0 - left.x1 >= cfg.segment_length_min
    ]


def _side_cut_fits(
    outline: str, lines: list[tuple[int, int]], long_len: int, top: int, cfg: ProceduralConfig
) -> list[list[Rect]]:
    """Cutouts of rows [0, top) that leave an L, T or U (or nothing for a rectangle).

    `lines` are (x0, x1) cut lines: a cutout to the right starts at x1, one to the left
    ends at x0. Every remaining stretch keeps at least a segment's length.
    """
    seg = cfg.segment_length_min
    if outline == "rectangle":
        return [[]]
    if outline == "L":
        return [[Rect(0, top, b, long_len)] for a, b in lines if a >= seg and long_len - b >= seg]
    pairs = [(p, q) for i, p in enumerate(lines) for q in lines[i + 1 :] if q[0] - p[1] >= seg]
    if outline == "T":
        return [
            [Rect(0, top, 0, p[0]), Rect(0, top, q[1], long_len)]
            for p, q in pairs
            if p[0] >= seg and long_len - q[1] >= seg
        ]
    return [[Rect(0, top, p[1], q[0])] for p, q in pairs if p[0] >= seg and long_len - q[1] >= seg]


def _free_cut_lines(
    rng: np.random.Generator, long_len: int, crossings: list[Rect], cfg: ProceduralConfig
) -> list[tuple[int, int]]:
    """A few cut positions at least a room width away from every cross corridor."""
    seg, clear = cfg.segment_length_min, cfg.room_width_min
    if long_len <= 2 * seg:
        return []
    xs = rng.integers(seg, long_len - seg, 4).tolist()
    return [(x, x) for x in xs if all(x <= c.x0 - clear or x >= c.x1 + clear for c in crossings)]


# ---------------------------------------------------------------- spaces


def _corridor_spaces(
    rng: np.random.Generator,
    long_len: int,
    bands: list[_Band],
    crossings: list[Rect],
    cfg: ProceduralConfig,
) -> list[_Space]:
    """Parallel and cross corridors, with the rooms that close some corridor ends."""
    spaces = [_Space(c, True) for c in crossings]
    for band in (b for b in bands if b.kind == "corridor"):
        x0, x1 = 0, long_len
        for at_start in (True, False):
            if rng.random() >= cfg.end_room_probability:
                continue
            length = int(rng.integers(cfg.end_room_length_min, cfg.end_room_length_max + 1))
            reach = length + cfg.room_width_min
            lo, hi = (0, reach) if at_start else (long_len - reach, long_len)
            if any(c.x0 < hi and c.x1 > lo for c in crossings):
                continue
            rect = (
                Rect(band.y0, band.y1, 0, length)
                if at_start
                else Rect(band.y0, band.y1, long_len - length, long_len)
            )
            side = "right" if at_start else "left"
            spaces.append(_Space(rect, False, door_side=side, door_width=_door_width(rng, cfg)))
            x0, x1 = (length, x1) if at_start else (x0, long_len - length)
        spaces.append(_Space(Rect(band.y0, band.y1, x0, x1), True))
    return spaces


def _room_spaces(
    rng: np.random.Generator,
    long_len: int,
    bands: list[_Band],
    crossings: list[Rect],
    cutouts: list[Rect],
    cfg: ProceduralConfig,
) -> list[_Space]:
    """Rooms and halls of every room row, block by block."""
    blocks = [
        (i, x0, x1)
        for i, band in enumerate(bands)
        if band.kind == "room"
        for x0, x1 in _band_blocks(band, long_len, crossings, cutouts, cfg)
    ]
    pieces = {block: [(block[1], block[2], "rooms")] for block in blocks}
    halls = _place_halls(rng, bands, blocks, pieces, cfg)
    modules = {
        i: int(rng.integers(cfg.room_module_min, cfg.room_module_max + 1))
        for i in sorted({block[0] for block in blocks})
    }
    spaces = [_Space(rect, False, door_width=_door_width(rng, cfg), is_hall=True) for rect in halls]
    for block in blocks:
        band = bands[block[0]]
        params = _block_params(rng, band, cfg)
        suite_front = _suite_front_depth(rng, band, cfg)
        for x0, x1, kind in pieces[block]:
            if kind != "rooms":
                continue
            for rx0, rx1 in _room_cuts(rng, x0, x1, modules[block[0]], cfg):
                spaces += _block_rooms(Rect(band.y0, band.y1, rx0, rx1), band, suite_front, params)
    return spaces


def _band_blocks(
    band: _Band,
    long_len: int,
    crossings: list[Rect],
    cutouts: list[Rect],
    cfg: ProceduralConfig,
) -> list[tuple[int, int]]:
    """[x0, x1) stretches of a room row between cross corridors and outside cutouts."""
    taken = [(c.x0, c.x1) for c in crossings if c.y0 < band.y1 and c.y1 > band.y0]
    taken += [(c.x0, c.x1) for c in cutouts if c.y0 <= band.y0 and band.y1 <= c.y1]
    points = sorted({0, long_len, *(x for pair in taken for x in pair)})
    return [
        (a, b)
        for a, b in zip(points, points[1:], strict=False)
        if b - a >= cfg.room_width_min and not any(lo <= a and b <= hi for lo, hi in taken)
    ]


def _place_halls(
    rng: np.random.Generator,
    bands: list[_Band],
    blocks: list[tuple[int, int, int]],
    pieces: dict[tuple[int, int, int], list[tuple[int, int, str]]],
    cfg: ProceduralConfig,
) -> list[Rect]:
    """Carve a few halls out of the blocks' room pieces; some span a back-to-back pair."""
    eligible = [b for b in blocks if b[2] - b[1] >= cfg.hall_length_min]
    if not eligible:
        return []
    n_halls = int(rng.integers(cfg.hall_count_min, cfg.hall_count_max + 1))
    n_halls = min(n_halls, len(blocks) // cfg.blocks_per_hall_min)
    chosen = rng.choice(len(eligible), size=min(n_halls, len(eligible)), replace=False)
    halls = []
    for block in (eligible[i] for i in sorted(chosen.tolist())):
        band_index, x0, x1 = block
        lo, hi = _hall_span(rng, x0, x1, cfg)
        if not _carve_piece(pieces[block], lo, hi, "hall"):
            continue
        band = bands[band_index]
        y0, y1 = band.y0, band.y1
        partner = (band.partner, x0, x1)
        merge = partner in pieces and rng.random() < cfg.merged_hall_probability
        if merge and _carve_piece(pieces[partner], lo, hi, "covered"):
            other = bands[band.partner]
            y0, y1 = min(y0, other.y0), max(y1, other.y1)
        halls.append(Rect(y0, y1, lo, hi))
    return halls


def _hall_span(
    rng: np.random.Generator, x0: int, x1: int, cfg: ProceduralConfig
) -> tuple[int, int]:
    """A hall's [lo, hi) inside a block, stretched to the block end over slivers."""
    longest = min(cfg.hall_length_max, x1 - x0)
    length = int(rng.integers(min(cfg.hall_length_min, longest), longest + 1))
    lo = int(rng.integers(x0, x1 - length + 1))
    hi = lo + length
    lo = x0 if lo - x0 < cfg.room_width_min else lo
    hi = x1 if x1 - hi < cfg.room_width_min else hi
    return lo, hi


def _carve_piece(pieces: list[tuple[int, int, str]], lo: int, hi: int, kind: str) -> bool:
    """Relabel [lo, hi) of the "rooms" piece that contains it; False when none does."""
    for i, (a, b, piece_kind) in enumerate(pieces):
        if piece_kind == "rooms" and a <= lo and hi <= b:
            parts = [(a, lo, "rooms"), (lo, hi, kind), (hi, b, "rooms")]
            pieces[i : i + 1] = [p for p in parts if p[1] > p[0]]
            return True
    return False


def _block_params(rng: np.random.Generator, band: _Band, cfg: ProceduralConfig) -> dict:
    """Door placement shared by the rooms of one block, so their doors line up."""
    return {
        "door_side": str(rng.choice(band.corridor_sides)) if band.corridor_sides else "top",
        "anchor": str(rng.choice(["low", "high", "centre"])),
        "offset": int(rng.integers(0, cfg.door_offset_max + 1)),
        "door_width": _door_width(rng, cfg),
    }


def _door_width(rng: np.random.Generator, cfg: ProceduralConfig) -> int:
    return int(rng.integers(cfg.door_width_min, cfg.door_width_max + 1))


def _suite_front_depth(rng: np.random.Generator, band: _Band, cfg: ProceduralConfig) -> int:
    """Depth of the front rooms when an outer row is split into front and inner rooms, or 0."""
    depth = band.y1 - band.y0
    outer = band.partner is None and len(band.corridor_sides) == 1
    if not outer or depth < 2 * cfg.suite_room_depth_min:
        return 0
    if rng.random() >= cfg.suite_probability:
        return 0
    fraction = rng.uniform(cfg.suite_front_fraction_min, cfg.suite_front_fraction_max)
    front = int(round(depth * fraction))
    return int(np.clip(front, cfg.suite_room_depth_min, depth - cfg.suite_room_depth_min))


def _room_cuts(
    rng: np.random.Generator, x0: int, x1: int, module: int, cfg: ProceduralConfig
) -> list[tuple[int, int]]:
    """Rooms of one or two modules along [x0, x1); the last absorbs a short remainder."""
    widths: list[int] = []
    left = x1 - x0
    while left > 0:
        double = rng.random() < cfg.double_room_probability
        width = 2 * module if double and 2 * module <= cfg.room_width_max else module
        if left - width < cfg.room_width_min:
            width = left
        widths.append(width)
        left -= width
    if rng.random() < 0.5:
        widths.reverse()
    ends = (x0 + np.cumsum(widths)).tolist()
    return list(zip([x0, *ends[:-1]], ends, strict=True))


def _block_rooms(rect: Rect, band: _Band, suite_front: int, params: dict) -> list[_Space]:
    """One room, or a front room on the corridor side plus the inner room behind it."""
    if not suite_front:
        return [_Space(rect, False, **params)]
    if band.corridor_sides == ("top",):
        front = rect._replace(y1=rect.y0 + suite_front)
        inner = rect._replace(y0=rect.y0 + suite_front)
    else:
        front = rect._replace(y0=rect.y1 - suite_front)
        inner = rect._replace(y1=rect.y1 - suite_front)
    return [_Space(front, False, **params), _Space(inner, False, **params)]


def _open_lobby(
    rng: np.random.Generator, spaces: list[_Space], edges: list[Edge], cfg: ProceduralConfig
) -> None:
    """Leave one plain room next to a corridor open to it (an open area)."""
    if rng.random() >= cfg.lobby_probability:
        return
    candidates = sorted(
        {e.a for e in edges if spaces[e.b].is_root and not spaces[e.a].is_root}
        - {i for i, s in enumerate(spaces) if s.is_hall}
    )
    if candidates:
        spaces[candidates[int(rng.integers(len(candidates)))]].is_root = True


# ---------------------------------------------------------------- geometry helpers


def _shift(rect: Rect, by: int) -> Rect:
    return Rect(rect.y0 + by, rect.y1 + by, rect.x0 + by, rect.x1 + by)


def _contains(outer: Rect, inner: Rect) -> bool:
    return (
        outer.y0 <= inner.y0
        and inner.y1 <= outer.y1
        and outer.x0 <= inner.x0
        and inner.x1 <= outer.x1
    )


def _shared_edges(rects: list[Rect], min_length: int) -> list[Edge]:
    """Every wall at least `min_length` long shared by two rectangles, once from each side."""
    y0, y1, x0, x1 = (np.array(v)[:, None] for v in zip(*rects, strict=True))
    x_lo, x_hi = np.maximum(x0, x0.T), np.minimum(x1, x1.T)
    y_lo, y_hi = np.maximum(y0, y0.T), np.minimum(y1, y1.T)
    below = (y1 == y0.T) & (x_hi - x_lo >= min_length)
    right = (x1 == x0.T) & (y_hi - y_lo >= min_length)
    edges = []
    for a, b in zip(*np.nonzero(below), strict=True):
        lo, hi, coord = int(x_lo[a, b]), int(x_hi[a, b]), int(y0[b, 0])
        edges += [Edge(int(a), int(b), "bottom", coord, lo, hi)]
        edges += [Edge(int(b), int(a), "top", coord, lo, hi)]
    for a, b in zip(*np.nonzero(right), strict=True):
        lo, hi, coord = int(y_lo[a, b]), int(y_hi[a, b]), int(x0[b, 0])
        edges += [Edge(int(a), int(b), "right", coord, lo, hi)]
        edges += [Edge(int(b), int(a), "left", coord, lo, hi)]
    return edges


# ---------------------------------------------------------------- rasterisation


def _paint_labels(spaces: list[_Space], cutouts: list[Rect], shape: tuple[int, int]) -> np.ndarray:
    """Label map: corridors and open areas first, then one label per room, cutouts last."""
    labels = np.zeros(shape, dtype=np.int32)
    next_label = FIRST_ROOM_LABEL
    for space in sorted(spaces, key=lambda s: not s.is_root):
        r = space.rect
        if space.is_root:
            labels[r.y0 : r.y1, r.x0 : r.x1] = CORRIDOR_LABEL
        else:
            labels[r.y0 : r.y1, r.x0 : r.x1] = next_label
            next_label += 1
    for r in cutouts:
        labels[r.y0 : r.y1, r.x0 : r.x1] = 0
    return labels


def _walls_from_labels(
    labels: np.ndarray, wall_cells: int, outer_wall_cells: int, wall_outside: bool
) -> np.ndarray:
    """Walls `wall_cells` thick on every change between two spaces, `outer_wall_cells`
    thick on the building's outline (a change to label 0), and (if `wall_outside`)
    everything outside the building.

    A change between rows y-1 and y of thickness n walls rows [y - n // 2, y - n // 2
    + n); columns likewise (the same rows a door through it opens).
    """
    walls = (labels == 0) if wall_outside else np.zeros(labels.shape, dtype=bool)
    for axis in (0, 1):
        n = labels.shape[axis]
        before, after = labels.take(range(n - 1), axis=axis), labels.take(range(1, n), axis=axis)
        differs = before != after
        on_outline = differs & ((before == 0) | (after == 0))
        for change, cells in ((differs & ~on_outline, wall_cells), (on_outline, outer_wall_cells)):
            mask = np.zeros(labels.shape, dtype=bool)  # the change sits at the later cell
            mask[(slice(None),) * axis + (slice(1, None),)] = change
            for k in range(cells):
                walls |= _shifted(mask, k - cells // 2, axis=axis)
    _close_diagonal_gaps(walls, labels)
    return walls


def _close_diagonal_gaps(walls: np.ndarray, labels: np.ndarray) -> None:
    """Wall the lower cell of every diagonal pair of free cells with different labels.

    Thin walls leave such pairs where a room corner meets a corridor corner; an
    8-connected robot would slip through them.
    """
    free = ~walls
    for upper, lower in (
        ((slice(None, -1), slice(None, -1)), (slice(1, None), slice(1, None))),
        ((slice(None, -1), slice(1, None)), (slice(1, None), slice(None, -1))),
    ):
        leak = free[upper] & free[lower] & (labels[upper] != labels[lower])
        walls[lower] |= leak


def _shifted(mask: np.ndarray, step: int, axis: int) -> np.ndarray:
    """`mask` moved `step` cells along `axis` (negative: towards index 0), zero-filled."""
    out = np.zeros_like(mask)
    n = mask.shape[axis]
    source, target = [slice(None)] * 2, [slice(None)] * 2
    source[axis] = slice(max(0, -step), n - max(0, step))
    target[axis] = slice(max(0, step), n - max(0, -step))
    out[tuple(target)] = mask[tuple(source)]
    return out


def _door_mask(
    rng: np.random.Generator,
    spaces: list[_Space],
    edges: list[Edge],
    wall_cells: int,
    shape: tuple[int, int],
    cfg: ProceduralConfig,
) -> np.ndarray:
    """Door openings: a spanning tree from the corridors plus hall and connecting doors."""
    doors = np.zeros(shape, dtype=bool)
    by_space: list[list[Edge]] = [[] for _ in spaces]
    for edge in edges:
        by_space[edge.a].append(edge)
    chosen = _spanning_doors(spaces, by_space) + _extra_doors(rng, spaces, by_space, cfg)
    for edge in chosen:
        r = _door_rect(edge, spaces[edge.a], wall_cells)
        doors[r.y0 : r.y1, r.x0 : r.x1] = True
    return doors


def _spanning_doors(spaces: list[_Space], by_space: list[list[Edge]]) -> list[Edge]:
    """One door per room, in waves out from the corridors: a corridor door when there is
    one (on the block's preferred side first), else the longest wall to a reached room."""
    reached = np.array([s.is_root for s in spaces])
    doors: list[Edge] = []
    while True:
        wave = []
        for i in np.flatnonzero(~reached):
            options = [e for e in by_space[i] if reached[e.b]]
            if options:
                wave.append(max(options, key=lambda e: _door_preference(spaces, e)))
        if not wave:
            return doors
        doors += wave
        reached[[e.a for e in wave]] = True


def _door_preference(spaces: list[_Space], edge: Edge) -> tuple[bool, bool, int]:
    return (spaces[edge.b].is_root, edge.side == spaces[edge.a].door_side, edge.hi - edge.lo)


def _extra_doors(
    rng: np.random.Generator,
    spaces: list[_Space],
    by_space: list[list[Edge]],
    cfg: ProceduralConfig,
) -> list[Edge]:
    """Halls open onto every corridor they touch; some rooms get a connecting door."""
    extra = []
    for i, space in enumerate(spaces):
        if space.is_root:
            continue
        if space.is_hall:
            extra += [e for e in by_space[i] if spaces[e.b].is_root]
        if rng.random() < cfg.extra_door_probability:
            rooms = [e for e in by_space[i] if not spaces[e.b].is_root]
            if rooms:
                extra.append(rooms[int(rng.integers(len(rooms)))])
    return extra


def _door_rect(edge: Edge, space: _Space, wall_cells: int) -> Rect:
    """The wall cells a door of `space` opens in `edge`, clear of the corners."""
    margin = wall_cells + 1
    width = min(space.door_width, edge.hi - edge.lo - 2 * margin)
    if space.anchor == "low":
        start = edge.lo + margin + space.offset
    elif space.anchor == "high":
        start = edge.hi - margin - space.offset - width
    else:
        start = (edge.lo + edge.hi - width) // 2
    start = int(np.clip(start, edge.lo + margin, edge.hi - margin - width))
    across = edge.coord - wall_cells // 2
    if edge.side in ("top", "bottom"):
        return Rect(across, across + wall_cells, start, start + width)
    return Rect(start, start + width, across, across + wall_cells)


def _seal_unreachable(occupancy: np.ndarray) -> np.ndarray:
    """Wall up free cells outside the largest 8-connected free region (a repair that the
    construction should never need)."""
    components, count = ndimage.label(~occupancy, structure=EIGHT_CONNECTED)
    if count <= 1:
        return occupancy
    sizes = np.bincount(components.ravel())
    sizes[0] = 0
    return occupancy | (components != int(np.argmax(sizes)))


def _orient(array: np.ndarray, transposed: bool, flip_rows: bool, flip_cols: bool) -> np.ndarray:
    if transposed:
        array = array.T
    if flip_rows:
        array = array[::-1]
    if flip_cols:
        array = array[:, ::-1]
    return np.ascontiguousarray(array)
