"""Every tunable number of the system, in one typed place.

Defaults follow docs/algorithms.md (units: cells of 0.1 m, steps of the episode).
Any field can be overridden from the command line as `section.field=value`
(see `apply_overrides`), e.g. `--set visibility.stop_rule=threshold`.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

StopRule = Literal["accumulate", "threshold"]
Precision = Literal["float32", "bfloat16"]
PRECISIONS: tuple[str, ...] = typing.get_args(Precision)
T = TypeVar("T")


@dataclass(frozen=True)
class SensorConfig:
    """The 2D LiDAR of docs/algorithms.md#sensor."""

    n_rays: int = 2500
    range_cells: int = 200  # 20 m


@dataclass(frozen=True)
class MotionConfig:
    """Robot motion per timestep (docs/algorithms.md#sensor)."""

    cells_per_step: int = 3


@dataclass(frozen=True)
class FrontierConfig:
    """Frontier clustering (docs/algorithms.md#frontiers): clusters of
    `max_dropped_cluster_cells` or fewer go.

    `small_clusters_last`: before a run ends early, the dropped clusters that touch unknown
    space across a cell side (a narrow door seen obliquely, not the unseen diagonal cell of
    a wall corner) are tried too, as a last resort.
    """

    max_dropped_cluster_cells: int = 10
    small_clusters_last: bool = True


@dataclass(frozen=True)
class NavigationConfig:
    """Planning cost map, A* and the goal-keeping rule (docs/algorithms.md#navigation)."""

    wall_inflation_cells: int = 1  # 3x3 inflation of known walls
    wall_clearance_cells: float = 5.0  # distance-transform cost fades out at this distance
    wall_cost_weight: float = 2.0  # extra cost per cell at the wall, linearly less to 0
    goal_reached_cells: float = 10.0  # 1 m
    goal_unknown_radius_cells: float = 10.0  # goal dropped when no unknown cell within 1 m


@dataclass(frozen=True)
class VisibilityConfig:
    """Frontier visibility raycasts of docs/algorithms.md#methods."""

    n_rays: int = 250
    range_cells: int = 200
    stop_rule: StopRule = "threshold"
    epsilon: float = 0.8  # stopping level of the probabilistic raycast
    occupied_threshold: float = 0.5  # thresholded P_t: p >= this blocks
    no_visibility_radius_cells: int = 50  # 5 m disc of the No Visibility ablation


@dataclass(frozen=True)
class IgHectorConfig:
    """IG-Hector: utility = gain - path_cost_weight * exploration-transform cost."""

    path_cost_weight: float = 1.0


@dataclass(frozen=True)
class UpenConfig:
    """UPEN: RRT over non-occupied cells, best variance-sum path, re-plan every few steps."""

    rrt_iterations: int = 300
    rrt_step_cells: float = 8.0
    replan_every_steps: int = 10


@dataclass(frozen=True)
class NetworkConfig:
    """Size of the LaMa-style generator (mapex/prediction/network.py)."""

    channels: int = 64
    n_blocks: int = 4  # FFC residual blocks
    downscale: int = 8  # the FFC trunk works at 1/downscale resolution (pixel unshuffle)
    global_ratio: float = 0.75  # share of channels in the spectral (global) branch
    refine_channels: int = 16  # full-resolution refinement of the upsampled logits
    context_cells: int = 32  # map around a predicted region that the network also sees
    # inference: average the logits over the map and the map turned by 180 degrees (two
    # forward passes); the network is not equivariant, and the two views' errors differ
    average_turned_view: bool = True


MemberSplit = Literal["thirds", "by_source"]


@dataclass(frozen=True)
class PredictorTrainingConfig:
    """Data and schedule of `python -m mapex.prediction.train` (docs/algorithms.md#prediction)."""

    procedural_worlds: int = 48  # generated:<first_procedural_seed + i>
    first_procedural_seed: int = 1000
    snapshot_methods: tuple[str, ...] = ("nearest", "observed_map")
    starts_per_world: int = 2  # procedural plans
    kth_starts_per_world: int = 4
    kth_share: float = 0.5  # share of training crops taken from KTH snapshots (if any)
    snapshot_steps: int = 1000
    snapshot_every_steps: int = 50
    crop_cells: int = 256
    frontier_share: float = 0.75  # crops centred near a frontier, the rest anywhere
    edge_overhang_cells: int = 64  # how far a crop may hang over the map's border
    batch_size: int = 8
    main_steps: int = 6000  # G, on all data
    member_steps: int = 1200  # G_1..G_3, each fine-tuning G on its part of the data
    members_from_main: bool = True  # G_1..G_3 fine-tune G (the paper's fine-tune one LaMa)
    # G_k's data: "by_source" = G_1 and G_2 one KTH training map each, G_3 the procedural
    # plans; "thirds" = the worlds whose index is k - 1 modulo 3.
    member_split: MemberSplit = "by_source"
    # Procedural plans with free space outside the building (generated-open:SEED), as in
    # the KTH maps, instead of solid wall.
    free_outside_plans: bool = True
    learning_rate: float = 2e-3
    warmup_share: float = 0.1  # of each run's steps spent raising the learning rate (one cycle)
    weight_decay: float = 1e-4
    wall_weight: float = 2.0  # BCE weight of wall cells (walls are the rarer class)
    member_wall_weight: float = 1.0  # the same for G_1..G_3's fine-tuning (plain cross-entropy)
    # After G_1..G_3 have started from it, G is polished: fine-tuned further with this
    # many steps of its loss plus `polish_soft_iou_weight` times a soft IoU of the walls
    # per crop (the metric the evaluation scores), at `polish_learning_rate`. 0: no polish.
    main_polish_steps: int = 1500
    polish_soft_iou_weight: float = 3.0
    polish_learning_rate: float = 1e-3
    # G is polished this many times from its base weights (seeds seed + 4, + 5, ...) and
    # g.pt is the mean of the polished weights (a uniform model soup). 1: one polish.
    polish_runs: int = 1
    calibrate_main: bool = True  # after training G, choose its decision threshold (IoU)
    calibration_snapshots: int = 200  # training snapshots G's threshold is chosen on
    calibration_thresholds: tuple[float, ...] = tuple(round(0.2 + 0.025 * i, 3) for i in range(17))
    checkpoint_every_steps: int = 100
    seed: int = 0
    data_workers: int = 0  # processes cutting crops (for a GPU); the count changes the crop order
    # Forward pass in training. "bfloat16" autocasts it (weights, loss and optimiser stay
    # float32): about twice as fast on CPUs with AVX512-BF16 and on GPUs (slower on other
    # CPUs). The shipped weights were trained in bfloat16; "float32" writes other weights.
    precision: Precision = "bfloat16"
    network: NetworkConfig = field(default_factory=NetworkConfig)  # size of every member


@dataclass(frozen=True)
class PredictorEvaluationConfig:
    """`python -m mapex.prediction.evaluate` (docs/algorithms.md#prediction): when snapshots are
    taken, and what
    counts as near the known map."""

    snapshot_times: tuple[int, ...] = (100, 300, 600)
    near_known_cells: int = 10  # 1 m: unknown cells this close to a known one are "near"
    target_margin_iou: float = 0.10  # the lead over the classical IoU that G should reach


@dataclass(frozen=True)
class MetricsConfig:
    """Metrics of docs/algorithms.md#metrics."""

    sample_every_steps: int = 50
    tu_every_steps: int = 100
    tu_goals: int = 100
    footprint_margin_cells: int = 3
    prediction_threshold: float = 0.5
    snapshot_steps: tuple[int, ...] = (200, 500, 1000)  # observed + G maps kept for the report


@dataclass(frozen=True)
class WorldConfig:
    """Start poses (docs/algorithms.md#worlds)."""

    start_clearance_cells: int = 3  # 0.3 m


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


InpaintMethod = Literal["ns", "telea"]


@dataclass(frozen=True)
class InpaintMemberConfig:
    """One member of the classical inpainting ensemble (mapex.prediction.classical)."""

    method: InpaintMethod = "ns"  # cv2.INPAINT_NS (Navier-Stokes) or cv2.INPAINT_TELEA
    radius_cells: int = 1  # cv2.inpaint neighbourhood radius, in working-scale cells
    scale: int = 1  # works at 1/scale resolution (walls block-max downsampled) when > 1
    band_cells: float = 8.0  # only unknown cells this close (map cells) to known ones are painted
    prior: float = 0.05  # wall probability of the unknown cells beyond the band
    wall_level: float = 0.5  # painted value mapped to 0.5 by a piecewise-linear contrast


@dataclass(frozen=True)
class ClassicalPredictorConfig:
    """The classical (non-learned) predictor ensemble; member 0 is G (best single setting)."""

    members: tuple[InpaintMemberConfig, ...] = (
        InpaintMemberConfig(method="ns", radius_cells=1, scale=1, band_cells=10.0, prior=0.05),
        InpaintMemberConfig(method="ns", radius_cells=3, scale=2, band_cells=6.0, prior=0.0),
        InpaintMemberConfig(method="ns", radius_cells=1, scale=4, band_cells=8.0, prior=0.1),
        InpaintMemberConfig(
            method="telea", radius_cells=1, scale=4, band_cells=6.0, prior=0.15, wall_level=0.3
        ),
    )


@dataclass(frozen=True)
class ServicesConfig:
    """Wire limits and Zenoh defaults of the distributed simulator (services/, docs/design.md)."""

    max_message_bytes: int = 32 * 2**20  # encoded payload cap, checked before unpacking
    max_decoded_bytes: int = 128 * 2**20  # cap on a message's decompressed array bytes
    compress_threshold_bytes: int = 4096  # arrays larger than this travel zlib-compressed
    zlib_level: int = 1  # fastest level: maps are mostly runs of one code
    hub_endpoint: str = "tcp/127.0.0.1:7447"  # well-known loopback endpoint served by services.up
    ephemeral_listen_endpoint: str = "tcp/127.0.0.1:0"  # default listener: loopback, any free port
    predict_timeout_s: float = 10.0  # per-member prediction query; a hung worker costs this once
    supervision_poll_s: float = 0.2  # services.up / evaluate: how often children are checked
    publish_period_s: float = 0.1  # planner -> viewers: at most one batch of maps per period
    predict_retries: int = 3  # re-sends of a query that no worker was routed (no reply at all)
    predict_retry_pause_s: float = 0.2  # before the first re-send; doubles for each next one
    liveliness_query_timeout_s: float = 2.0  # planner's start-up discovery of live workers
    predictor_threads: int = 1  # torch CPU threads of one predictor worker (docs/design.md)
    predictor_drain_s: float = 3.0  # on shutdown, wait this long for the query being computed
    world_drain_s: float = 2.0  # on shutdown, wait this long for the step being answered
    step_timeout_s: float = 10.0  # one step query; a lost reply is retried with the same seq
    step_retries: int = 3  # attempts per step before the planner gives up on the world
    world_wait_s: float = 60.0  # planner start-up: how long to wait for the world's keys
    workers_wait_s: float = 120.0  # planner start-up: how long to wait for every member
    supervisor_max_restarts: int = 5  # a crashed server is restarted this often, then left dead
    stop_grace_s: float = 3.0  # services.up: SIGTERM, wait this long, then SIGKILL what is left
    hub_probe_timeout_s: float = 1.0  # connect probe of a hub port that a bind probe found taken


@dataclass(frozen=True)
class WatchConfig:
    """The live viewer `services.watch`: how often it renders, how big, how many GIF frames."""

    every_s: float = 1.0  # render at most this often (only when something new arrived)
    poll_s: float = 0.1  # how often the loop looks at arrivals (reaction time to "finished")
    get_timeout_s: float = 2.0  # late-joiner query; topics still unheard are re-asked this often
    inbox_depth: int = 8  # newest payloads kept per topic between polls (a bad one hides no good)
    dpi: int = 80
    panel_inches: float = 4.0  # width of one map panel
    max_gif_frames: int = 300  # at the cap every other frame is dropped (memory stays bounded)
    gif_max_side_px: int = 480  # GIF frames are downscaled to fit this square
    gif_frame_ms: int = 200


@dataclass(frozen=True)
class ReportConfig:
    """The evaluation report `python -m mapex.report`: figure settings and snapshot steps."""

    snapshot_steps: tuple[int, ...] = (200, 500, 1000)  # columns of snapshots.png
    dpi: int = 120
    curve_panel_inches: float = 4.0  # width (and height) of one metric panel of curves.png
    snapshot_panel_inches: float = 2.2  # width of one map panel of snapshots.png
    # maps wider than this (cols / rows) get one snapshots.png row per (method, map kind)
    snapshot_wide_aspect: float = 2.0
    snapshot_wide_panel_inches: float = 6.0  # width of one map panel in that wide layout
    snapshot_wide_row_gap_inches: float = 0.2  # space between the rows of that wide layout
    band_alpha: float = 0.2  # opacity of the standard-error bands

    @property
    def method_order(self) -> tuple[str, ...]:
        """Rows of every table and figure: the main comparison, then the ablations."""
        from mapex.methods import ABLATIONS, MAIN_COMPARISON  # mapex.methods imports config

        return MAIN_COMPARISON + ABLATIONS


@dataclass(frozen=True)
class ExplorationConfig:
    """The whole configuration of one exploration episode."""

    steps: int = 1000
    sensor: SensorConfig = field(default_factory=SensorConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    frontier: FrontierConfig = field(default_factory=FrontierConfig)
    navigation: NavigationConfig = field(default_factory=NavigationConfig)
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)
    ig_hector: IgHectorConfig = field(default_factory=IgHectorConfig)
    upen: UpenConfig = field(default_factory=UpenConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    world: WorldConfig = field(default_factory=WorldConfig)


class ConfigError(ValueError):
    """A configuration override that names no field or has a value of the wrong type."""


def apply_overrides(config: Any, overrides: list[str]) -> Any:
    """Return `config` with each `dotted.path=value` override applied (typed, validated)."""
    for item in overrides:
        path, sep, raw = item.partition("=")
        if not sep or not path:
            raise ConfigError(f"override '{item}' is not of the form section.field=value")
        config = _replace_path(config, path.split("."), raw, item)
    return config


def _replace_path(node: Any, parts: list[str], raw: str, item: str) -> Any:
    name = parts[0]
    fields = {f.name: f for f in dataclasses.fields(node)} if dataclasses.is_dataclass(node) else {}
    if name not in fields:
        known = ", ".join(sorted(fields)) or "none"
        raise ConfigError(f"override '{item}': unknown field '{name}' (known: {known})")
    hints = typing.get_type_hints(type(node))
    if len(parts) == 1:
        value = _coerce(raw, hints[name], item)
    else:
        value = _replace_path(getattr(node, name), parts[1:], raw, item)
    return dataclasses.replace(node, **{name: value})


def _coerce(raw: str, hint: Any, item: str) -> Any:
    origin = typing.get_origin(hint)
    if origin is Literal:
        if raw not in typing.get_args(hint):
            raise ConfigError(f"override '{item}': choose one of {typing.get_args(hint)}")
        return raw
    if origin in (typing.Union, types.UnionType):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    if typing.get_origin(hint) is tuple:  # tuple[X, ...]: comma-separated values
        item_hint = typing.get_args(hint)[0]
        return tuple(_coerce(part.strip(), item_hint, item) for part in raw.split(","))
    try:
        if hint is bool:
            if raw.lower() not in ("true", "false", "1", "0"):
                raise ValueError
            return raw.lower() in ("true", "1")
        return hint(raw)
    except (TypeError, ValueError):
        raise ConfigError(f"override '{item}': '{raw}' is not a valid {hint.__name__}") from None


def argparse_type(parse: Callable[[str], T]) -> Callable[[str], T]:
    """An argparse `type=` from a parser that raises ValueError with a one-line message, so
    argparse shows that message (it hides a plain ValueError's)."""

    def checked(text: str) -> T:
        try:
            return parse(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    checked.__name__ = parse.__name__
    return checked


def add_override_argument(parser: argparse.ArgumentParser) -> None:
    """--set SECTION.FIELD=VALUE (repeatable) into `args.overrides` (see `apply_overrides`)."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="override a configuration field, e.g. visibility.stop_rule=accumulate (repeatable)",
    )


def add_precision_argument(parser: argparse.ArgumentParser) -> None:
    """--precision of the learned ensemble's forward pass into `args.precision`."""
    parser.add_argument(
        "--precision",
        default="float32",
        choices=PRECISIONS,
        help="forward pass: float32 (default; the README's figures) or bfloat16 (about 2x "
        "faster on CPUs with AVX512-BF16/AMX and on GPUs, slower on other CPUs)",
    )
