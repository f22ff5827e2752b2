"""The configuration of an exploration episode, and the override machinery of every command.

Every tunable number is a field of a frozen dataclass, next to the code that uses it: the
episode's here (`ExplorationConfig`), the predictors' in `mapex/prediction/config.py`, the
procedural plans' in `mapex/worlds/config.py`, the report's in `mapex/report/config.py` and
the services' in `services/config.py`. Defaults follow docs/algorithms.md (units: cells of
0.1 m, steps of the episode). Any field can be overridden from the command line as
`section.field=value` (see `apply_overrides`), e.g. `--set visibility.stop_rule=threshold`.
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
MAX_RAYS = 100_000  # a scan's rays (the wire carries one uint16 length per ray)
MAX_RANGE_CELLS = 65_535  # the longest ray a uint16 length holds
T = TypeVar("T")


@dataclass(frozen=True)
class SensorConfig:
    """The 2D LiDAR of docs/algorithms.md#sensor."""

    n_rays: int = 2500
    range_cells: int = 200  # 20 m

    def __post_init__(self) -> None:
        if not 1 <= self.n_rays <= MAX_RAYS:
            raise ConfigError(f"sensor.n_rays must be in 1..{MAX_RAYS}, got {self.n_rays}")
        if not 1 <= self.range_cells <= MAX_RANGE_CELLS:
            raise ConfigError(
                f"sensor.range_cells must be in 1..{MAX_RANGE_CELLS}, got {self.range_cells}"
            )


@dataclass(frozen=True)
class MotionConfig:
    """Robot motion per timestep (docs/algorithms.md#sensor)."""

    cells_per_step: int = 3

    def __post_init__(self) -> None:
        if self.cells_per_step < 1:
            raise ConfigError(f"motion.cells_per_step must be >= 1, got {self.cells_per_step}")


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
class PipeConfig:
    """pipe and pw_nbv (docs/algorithms.md#pipe): their `pathwise_index`."""

    path_sample_cells: int = 3  # a viewpoint on every 3rd cell of the path

    def __post_init__(self) -> None:
        if self.path_sample_cells < 1:
            raise ConfigError(f"pipe.path_sample_cells must be >= 1, got {self.path_sample_cells}")


@dataclass(frozen=True)
class PathGainConfig:
    """mapex_plus: gain along the path to a frontier, per unit path cost
    (docs/algorithms.md#beyond-the-paper). Chosen on generated worlds and the trainable KTH
    floors only."""

    # beta in [0, 1]: a cell's worth is (1 - beta) x 1 (expected new area) + beta x V_t / mean
    # V_t over unknown cells (ensemble disagreement); 0 = area only, 1 = variance only
    variance_weight: float = 0.5
    path_sample_cells: int = 10  # one viewpoint every 1 m of path (plus the frontier)
    top_k: int = 8  # frontiers (best frontier-only score) whose path gain is computed
    # score = gain / (path cost + offset): an offset > 0 stops a tiny gain next to the robot
    # from outranking a large one a little further away (0 = plain gain per cell of path)
    cost_offset_cells: float = 20.0  # 2 m
    # the path cost divided by: "planner" (its wall-penalised cost) or "cells" (its length
    # in cells, as PIPE)
    cost_measure: Literal["planner", "cells"] = "planner"
    # re-plan every this many steps even while the goal still has unknown cells (0 = only
    # when the goal is reached or spent, as mapex): what the drive reveals can redirect it
    replan_every_steps: int = 20

    def __post_init__(self) -> None:
        if not 0.0 <= self.variance_weight <= 1.0:
            raise ConfigError(
                f"path_gain.variance_weight must be in [0, 1], got {self.variance_weight}"
            )
        if self.path_sample_cells < 1:
            raise ConfigError(
                f"path_gain.path_sample_cells must be >= 1, got {self.path_sample_cells}"
            )
        if self.top_k < 1:
            raise ConfigError(f"path_gain.top_k must be >= 1, got {self.top_k}")
        if not self.cost_offset_cells >= 0.0:
            raise ConfigError(
                f"path_gain.cost_offset_cells must be >= 0, got {self.cost_offset_cells}"
            )
        if self.replan_every_steps < 0:
            raise ConfigError(
                f"path_gain.replan_every_steps must be >= 0, got {self.replan_every_steps}"
            )


@dataclass(frozen=True)
class UpenConfig:
    """UPEN: RRT over non-occupied cells, best variance-sum path, re-plan every few steps."""

    rrt_iterations: int = 300
    rrt_step_cells: float = 8.0
    replan_every_steps: int = 10


@dataclass(frozen=True)
class MetricsConfig:
    """Metrics of docs/algorithms.md#metrics."""

    sample_every_steps: int = 50
    tu_every_steps: int = 100
    tu_goals: int = 100
    footprint_margin_cells: int = 3
    prediction_threshold: float = 0.5
    snapshot_steps: tuple[int, ...] = (200, 500, 1000)  # observed + G maps kept for the report
    # the first step at which coverage and G's IoU reach each level is recorded (to the step)
    reach_levels: tuple[float, ...] = (0.90, 0.95)

    def __post_init__(self) -> None:
        if self.sample_every_steps < 1:
            raise ConfigError(
                f"metrics.sample_every_steps must be >= 1, got {self.sample_every_steps}"
            )
        if not all(0.0 < level <= 1.0 for level in self.reach_levels):
            raise ConfigError(f"metrics.reach_levels must be in (0, 1], got {self.reach_levels}")


@dataclass(frozen=True)
class WorldConfig:
    """Start poses (docs/algorithms.md#worlds)."""

    start_clearance_cells: int = 3  # 0.3 m
    # worlds above this many cells are refused: a whole-map prediction grows with the area
    # (about 0.4 s per member for 50015847's 0.59 M cells on one CPU thread) and would miss
    # the query timeout; the largest development map (IPA office_g) has 1.2 M
    max_cells: int = 4_000_000

    def __post_init__(self) -> None:
        if self.max_cells < 1:
            raise ConfigError(f"world.max_cells must be >= 1, got {self.max_cells}")


@dataclass(frozen=True)
class TeamConfig:
    """Several robots sharing one map (docs/algorithms.md#teams)."""

    spacing_cells: int = 10  # default deployment: robots about 1 m apart near the start
    goal_exclusion_cells: int = 20  # nearest_team: skip frontiers within 2 m of a teammate's goal
    # a teammate's new claim makes a robot re-plan when it lies this close to its own goal
    # and scores better
    claim_conflict_cells: int = 20
    # mapex_team / mapex_plus_team: also claim what the robot will see on its way, from
    # every k-th cell of its path to the goal (0: the goal's visible set only, issue #41's
    # first definition; 10 lowers two robots' overlap 0.720 -> 0.688, docs/results/teams.md)
    claim_path_every_cells: int = 10
    # the team predicts on its map as it stood at the last multiple of this many steps, once
    # per such epoch for every robot re-planning in it (cells observed since are copied
    # through); 1: each re-plan predicts on the current map, as single-robot `mapex` (and
    # a team of one) does.
    # 10 cuts a 4-robot step through services.up from 2.6 x to 1.7 x one robot's, with two
    # robots' AUCs unchanged within noise (docs/results/teams.md)
    prediction_epoch_steps: int = 10

    def __post_init__(self) -> None:
        names = ("spacing_cells", "goal_exclusion_cells", "claim_conflict_cells")
        for name in (*names, "prediction_epoch_steps"):
            if getattr(self, name) < 1:
                raise ConfigError(f"team.{name} must be >= 1, got {getattr(self, name)}")
        if self.claim_path_every_cells < 0:
            raise ConfigError(
                f"team.claim_path_every_cells must be >= 0, got {self.claim_path_every_cells}"
            )


@dataclass(frozen=True)
class ExplorationConfig:
    """The whole configuration of one exploration episode."""

    steps: int = 1000
    # end the run once G's IoU reaches this level (the authors' IoU-stop protocol); None: never
    until_iou: float | None = None
    sensor: SensorConfig = field(default_factory=SensorConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    frontier: FrontierConfig = field(default_factory=FrontierConfig)
    navigation: NavigationConfig = field(default_factory=NavigationConfig)
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)
    ig_hector: IgHectorConfig = field(default_factory=IgHectorConfig)
    path_gain: PathGainConfig = field(default_factory=PathGainConfig)
    pipe: PipeConfig = field(default_factory=PipeConfig)
    upen: UpenConfig = field(default_factory=UpenConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    world: WorldConfig = field(default_factory=WorldConfig)
    team: TeamConfig = field(default_factory=TeamConfig)

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ConfigError(f"steps must be at least 1, got {self.steps}")
        if self.until_iou is not None and not 0.0 < self.until_iou <= 1.0:
            raise ConfigError(f"until_iou must be in (0, 1], got {self.until_iou}")


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
