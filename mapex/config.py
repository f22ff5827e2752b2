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
import functools
import math
import numbers
import os
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, TypeVar

StopRule = Literal["accumulate", "threshold"]
MAX_RAYS = 100_000  # a scan's rays (the wire carries one uint16 length per ray)
MAX_RANGE_CELLS = 65_535  # the longest ray a uint16 length holds
MAX_SEED = 2**32 - 1  # seeds (`--seed`, `--seeds`, `seed=`): what every random generator takes
# processes a command may start (planners, worlds, workers, audit jobs): at most this many per
# CPU core, and no more than the machine's memory holds at this much each (a planner on a
# default world peaks at about 450 MB, most of it torch and numba)
MAX_PROCESSES_PER_CPU = 8
PROCESS_MEMORY_BYTES = 512 * 2**20
RANGE = "range"  # field metadata key of a field's `Range` (see `ranged`)
T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration override that names no field or has a value of the wrong type."""


@dataclass(frozen=True)
class Range:
    """The values a numeric field (or each item of a tuple field) may take: `low` and
    `high` inclusive (None: unbounded), `low` excluded when `low_open` (a duration: > 0),
    `high` when `high_open`. `text` replaces the generated wording ("must be at least 1")."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    text: str | None = None

    def holds(self, value: float) -> bool:
        """Whether `value` is in the range (NaN never is)."""
        if math.isnan(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open else value <= self.high)

    def __str__(self) -> str:
        if self.text is not None:
            return self.text
        if self.low is not None and self.high is not None:
            opening, closing = "(["[not self.low_open], ")]"[not self.high_open]
            return f"in {opening}{self.low}, {self.high}{closing}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {self.low}"
        return f"{'<' if self.high_open else '<='} {self.high}"


def ranged(
    default: T,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
    text: str | None = None,
) -> T:
    """A dataclass field with `default` whose values (or tuple items) must lie in
    [low, high] (`Range`); `Checked.__post_init__` enforces it."""
    return field(default=default, metadata={RANGE: Range(low, high, low_open, high_open, text)})


def positive(default: T) -> T:
    """A field above 0 (a duration, a weight that divides): `ranged(default, 0, low_open=True)`."""
    return ranged(default, 0, low_open=True)


def share(default: T) -> T:
    """A field in [0, 1] (a probability, a fraction, a level)."""
    return ranged(default, 0, 1)


class Checked:
    """The base of every configuration dataclass: building one checks every field (type and
    declared `Range`, finite numbers, `x_min <= x_max` pairs) and raises a one-line
    ConfigError naming `SECTION.field`, so a bad `--set` stops a command before any work."""

    SECTION: ClassVar[str] = ""  # the `--set` prefix of this dataclass's fields ("" at the top)

    def __post_init__(self) -> None:
        check_fields(self)


def check_fields(config: Any) -> None:
    """ConfigError (one line) for the first field of the dataclass `config` whose value is
    not of its annotated type, lies outside its `Range` (field metadata), is a non-finite
    float, or is a `..._min` above its `..._max` (or `min_...` above `max_...`)."""
    prefix = f"{config.SECTION}." if getattr(config, "SECTION", "") else ""
    for each, hint in _field_hints(type(config)):
        value = getattr(config, each.name)
        name = f"{prefix}{each.name}"
        expected = _type_problem(value, hint)
        if expected is not None:
            raise ConfigError(f"{name} must be {expected}, got {value!r}")
        bounds = each.metadata.get(RANGE)
        for number in _numbers(value):
            if bounds is not None and not bounds.holds(number):
                raise ConfigError(f"{name} must be {bounds}, got {_shown(value)}")
            if not math.isfinite(number):
                raise ConfigError(f"{name} must be a finite number, got {_shown(value)}")
    for low_name, high_name in _min_max_pairs(type(config)):
        low, high = getattr(config, low_name), getattr(config, high_name)
        if low is not None and high is not None and low > high:
            raise ConfigError(
                f"{prefix}{low_name} ({low}) must not exceed {prefix}{high_name} ({high})"
            )


@functools.cache
def _field_hints(cls: type) -> tuple[tuple[dataclasses.Field, Any], ...]:
    hints = typing.get_type_hints(cls)
    return tuple((each, hints[each.name]) for each in dataclasses.fields(cls))


@functools.cache
def _min_max_pairs(cls: type) -> tuple[tuple[str, str], ...]:
    names = [each.name for each in dataclasses.fields(cls)]
    pairs = []
    for name in names:
        words = name.split("_")
        if "min" in words:
            other = "_".join("max" if word == "min" else word for word in words)
            if other in names:
                pairs.append((name, other))
    return tuple(pairs)


def _shown(value: Any) -> str:
    return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def _numbers(value: Any) -> list[float]:
    """The numbers a checked value holds: itself, or a tuple's numeric items (recursively)."""
    if isinstance(value, tuple):
        return [number for item in value for number in _numbers(item)]
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return [value]
    return []


def _type_problem(value: Any, hint: Any) -> str | None:
    """What `value` should be when it is not of the annotated type `hint` (else None)."""
    origin = typing.get_origin(hint)
    if origin is Literal:
        choices = typing.get_args(hint)
        return None if value in choices else f"one of {', '.join(map(repr, choices))}"
    if origin in (typing.Union, types.UnionType):
        arms = typing.get_args(hint)
        if value is None and type(None) in arms:
            return None
        problems = [_type_problem(value, arm) for arm in arms if arm is not type(None)]
        return None if None in problems else " or ".join(p for p in problems if p)
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, tuple):
            return "a tuple (comma-separated values)"
        items = args[:1] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        if len(items) != len(value):
            return f"{len(items)} comma-separated values"
        problems = [_type_problem(item, each) for item, each in zip(value, items, strict=True)]
        found = next((p for p in problems if p is not None), None)
        return None if found is None else f"a tuple of items each {found}"
    if hint is bool:
        return None if isinstance(value, bool) else "true or false"
    if hint is int:
        integral = isinstance(value, numbers.Integral) and not isinstance(value, bool)
        return None if integral else "an integer"
    if hint is float:
        real = isinstance(value, numbers.Real) and not isinstance(value, bool)
        return None if real else "a number"
    if hint is str:
        return None if isinstance(value, str) else "a string"
    if isinstance(hint, type):
        return None if isinstance(value, hint) else f"a {hint.__name__}"
    return None


def usable_cpus() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def physical_memory_bytes() -> int:
    """The machine's physical memory (0 where the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 0


def check_process_count(
    count: int,
    what: str,
    per_cpu: int = MAX_PROCESSES_PER_CPU,
    memory_each: int = PROCESS_MEMORY_BYTES,
    settings: str = "",
) -> None:
    """ConfigError (one line) when `count` processes, asked for by `what` (the flags), are
    more than this machine holds: `per_cpu` per usable CPU core, and its memory at
    `memory_each` bytes each. `settings` names the `--set` items that raise the caps."""
    cpus, memory = usable_cpus(), physical_memory_bytes()
    by_cpu = cpus * per_cpu
    cap = max(1, min(by_cpu, memory // memory_each if memory else by_cpu))
    if count > cap:
        raise ConfigError(
            f"{what}: {count} processes, more than this machine holds ({cap}: {per_cpu} "
            f"per CPU x {cpus} CPUs, {memory / 2**30:.0f} GiB at {memory_each / 2**20:.0f} MiB "
            f"each" + (f"; {settings} raise the caps)" if settings else ")")
        )


def parse_seed(text: str) -> int:
    """A seed from the command line: an integer in 0..MAX_SEED (ValueError, one line)."""
    try:
        seed = int(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a seed (an integer in 0..{MAX_SEED})") from None
    if not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed {seed} is out of range: seeds are integers in 0..{MAX_SEED}")
    return seed


@dataclass(frozen=True)
class SensorConfig(Checked):
    """The 2D LiDAR of docs/algorithms.md#sensor."""

    SECTION = "sensor"
    n_rays: int = ranged(2500, 1, MAX_RAYS)
    range_cells: int = ranged(200, 1, MAX_RANGE_CELLS)  # 20 m


@dataclass(frozen=True)
class MotionConfig(Checked):
    """Robot motion per timestep (docs/algorithms.md#sensor)."""

    SECTION = "motion"
    cells_per_step: int = ranged(3, 1, MAX_RANGE_CELLS)


@dataclass(frozen=True)
class FrontierConfig(Checked):
    """Frontier clustering (docs/algorithms.md#frontiers): clusters of
    `max_dropped_cluster_cells` or fewer go.

    `small_clusters_last`: before a run ends early, the dropped clusters that touch unknown
    space across a cell side (a narrow door seen obliquely, not the unseen diagonal cell of
    a wall corner) are tried too, as a last resort.
    """

    SECTION = "frontier"
    max_dropped_cluster_cells: int = ranged(10, 0)
    small_clusters_last: bool = True


@dataclass(frozen=True)
class NavigationConfig(Checked):
    """Planning cost map, A* and the goal-keeping rule (docs/algorithms.md#navigation)."""

    SECTION = "navigation"
    wall_inflation_cells: int = ranged(1, 0)  # 3x3 inflation of known walls
    # distance-transform cost fades out at this distance
    wall_clearance_cells: float = positive(5.0)
    wall_cost_weight: float = ranged(2.0, 0)  # extra cost per cell at the wall, linearly less to 0
    goal_reached_cells: float = ranged(10.0, 0)  # 1 m
    # goal dropped when no unknown cell within 1 m
    goal_unknown_radius_cells: float = ranged(10.0, 0)


@dataclass(frozen=True)
class VisibilityConfig(Checked):
    """Frontier visibility raycasts of docs/algorithms.md#methods."""

    SECTION = "visibility"
    n_rays: int = ranged(250, 1, MAX_RAYS)
    range_cells: int = ranged(200, 1, MAX_RANGE_CELLS)
    stop_rule: StopRule = "threshold"
    epsilon: float = ranged(0.8, 0, 1, low_open=True)  # stopping level of the probabilistic raycast
    occupied_threshold: float = share(0.5)  # thresholded P_t: p >= this blocks
    no_visibility_radius_cells: int = ranged(50, 0)  # 5 m disc of the No Visibility ablation


@dataclass(frozen=True)
class IgHectorConfig(Checked):
    """IG-Hector: utility = gain - path_cost_weight * exploration-transform cost."""

    SECTION = "ig_hector"
    path_cost_weight: float = ranged(1.0, 0)


@dataclass(frozen=True)
class PipeConfig(Checked):
    """pipe and pw_nbv (docs/algorithms.md#pipe): their `pathwise_index`."""

    SECTION = "pipe"
    path_sample_cells: int = ranged(3, 1)  # a viewpoint on every 3rd cell of the path


@dataclass(frozen=True)
class PathGainConfig(Checked):
    """mapex_plus: gain along the path to a frontier, per unit path cost
    (docs/algorithms.md#beyond-the-paper). Chosen on generated worlds and the trainable KTH
    floors only."""

    SECTION = "path_gain"
    # beta in [0, 1]: a cell's worth is (1 - beta) x 1 (expected new area) + beta x V_t / mean
    # V_t over unknown cells (ensemble disagreement); 0 = area only, 1 = variance only
    variance_weight: float = share(0.5)
    path_sample_cells: int = ranged(10, 1)  # one viewpoint every 1 m of path (plus the frontier)
    top_k: int = ranged(8, 1)  # frontiers (best frontier-only score) whose path gain is computed
    # score = gain / (path cost + offset): an offset > 0 stops a tiny gain next to the robot
    # from outranking a large one a little further away (0 = plain gain per cell of path)
    cost_offset_cells: float = ranged(20.0, 0)  # 2 m
    # the path cost divided by: "planner" (its wall-penalised cost) or "cells" (its length
    # in cells, as PIPE)
    cost_measure: Literal["planner", "cells"] = "planner"
    # re-plan every this many steps even while the goal still has unknown cells (0 = only
    # when the goal is reached or spent, as mapex): what the drive reveals can redirect it
    replan_every_steps: int = ranged(20, 0)


@dataclass(frozen=True)
class UpenConfig(Checked):
    """UPEN: RRT over non-occupied cells, best variance-sum path, re-plan every few steps."""

    SECTION = "upen"
    rrt_iterations: int = ranged(300, 1)
    rrt_step_cells: float = positive(8.0)
    replan_every_steps: int = ranged(10, 1)


@dataclass(frozen=True)
class MetricsConfig(Checked):
    """Metrics of docs/algorithms.md#metrics."""

    SECTION = "metrics"
    sample_every_steps: int = ranged(50, 1)
    # a sample is completed (and published) this many steps after it was taken: G's whole-map
    # prediction asked for at the sample is computed by the workers meanwhile (~0.27 s, about
    # 10 steps of a distributed run), so a live view trails the run by this, not by a period
    complete_after_steps: int = ranged(10, 1)
    tu_every_steps: int = ranged(100, 1)
    tu_goals: int = ranged(100, 1)
    footprint_margin_cells: int = ranged(3, 0)
    prediction_threshold: float = share(0.5)
    # observed + G maps kept for the report
    snapshot_steps: tuple[int, ...] = ranged((200, 500, 1000), 0)
    # the first step at which coverage and G's IoU reach each level is recorded (to the step)
    reach_levels: tuple[float, ...] = ranged((0.80, 0.90, 0.95), 0, 1, low_open=True)
    # end a run at the step its coverage reaches this level (None: run to T); a run to a
    # coverage level needs no step after it (docs/algorithms.md#time-to-level)
    until_coverage: float | None = ranged(None, 0, 1, low_open=True)


@dataclass(frozen=True)
class WorldConfig(Checked):
    """Start poses (docs/algorithms.md#worlds), and the limits on what is read: a world's
    cells and a file's bytes (`mapex.io_limits`)."""

    SECTION = "world"
    start_clearance_cells: int = ranged(3, 0)  # 0.3 m
    # worlds above this many cells are refused: a whole-map prediction grows with the area
    # (about 0.4 s per member for 50015847's 0.59 M cells on one CPU thread) and would miss
    # the query timeout; the largest development map (IPA office_g) has 1.2 M. Map files are
    # checked against it from their headers, before their data is read.
    max_cells: int = ranged(4_000_000, 1)
    # a file the project reads (a starts file, a configuration, a map's metadata, a run's
    # metrics or curves) larger than this is refused before it is read; map arrays are held
    # to max_cells instead
    max_file_bytes: int = ranged(64 * 2**20, 1)
    # an evaluation's starts (a starts file's, all maps together, or --starts) above this are
    # refused before any is judged: each is at least one episode per method and seed
    max_starts: int = ranged(10_000, 1)

    def check_starts(self, starts: int, what: str) -> None:
        """ConfigError (`too_many_starts`) when `starts`, the starts of `what`, are more
        than `max_starts`."""
        if starts > self.max_starts:
            raise ConfigError(self.too_many_starts(f"{what} ({starts})"))

    def too_many_starts(self, what: str) -> str:
        """The one line refusing `what` for holding more than `max_starts` starts."""
        return (
            f"{what}: more than world.max_starts ({self.max_starts}) starts; "
            f"--set world.max_starts=N raises the cap"
        )


@dataclass(frozen=True)
class TeamConfig(Checked):
    """Several robots sharing one map (docs/algorithms.md#teams)."""

    SECTION = "team"
    spacing_cells: int = ranged(10, 1)  # default deployment: robots about 1 m apart near the start
    # nearest_team: skip frontiers within 2 m of a teammate's goal (mapex_assign: taken)
    goal_exclusion_cells: int = ranged(20, 1)
    # a teammate's new claim makes a robot re-plan when it lies this close to its own goal
    # and scores better
    claim_conflict_cells: int = ranged(20, 1)
    # mapex_team / mapex_plus_team: also claim what the robot will see on its way, from
    # every k-th cell of its path to the goal (0: the goal's visible set only, issue #41's
    # first definition; 10 lowers two robots' overlap 0.720 -> 0.688, docs/results/teams.md)
    claim_path_every_cells: int = ranged(10, 0)
    # the team predicts on its map as it stood at the last multiple of this many steps, once
    # per such epoch for every robot re-planning in it (cells observed since are copied
    # through); 1: each re-plan predicts on the current map, as single-robot `mapex` (and
    # a team of one) does.
    # 10 cuts a 4-robot step through services.up from 2.6 x to 1.7 x one robot's, with two
    # robots' AUCs unchanged within noise (docs/results/teams.md)
    prediction_epoch_steps: int = ranged(10, 1)
    # mapex_assign: every robot re-plans at the steps t with t % this == 0, all computing
    # the same assignment of robots to frontiers (0: only when a robot's goal ends)
    assign_every_steps: int = ranged(0, 0)
    # mapex_assign: a frontier within `goal_exclusion_cells` of a teammate's goal is taken
    # (worth nothing to the others); its worth grows linearly to full at this distance
    # (Burgard et al. 2005's diminishing utility)
    assign_discount_cells: int = ranged(60, 1)
    # mapex_assign: also claim the goal's and the way's visible set (as mapex_team) and leave
    # the cells teammates holding a goal claimed out of the gain; on the development runs two
    # robots reach 90 % coverage 2.09 x sooner than one with it, 1.95 x without, and overlap
    # less (docs/results/teams.md)
    assign_claims_visible: bool = True
    # mapex_voronoi: the robots' path-distance cells run over the known free cells and the
    # unknown ones with a predicted occupancy below this
    region_wall_probability: float = share(0.5)
    # a robot with nothing to do for now (mapex_assign, mapex_voronoi) looks again after
    # this many steps
    idle_replan_steps: int = ranged(5, 1)
    # the largest team: every robot is a planner process in the services, and each robot
    # re-plans on the shared map (`--robots` above it is refused with one line)
    max_robots: int = ranged(64, 1)

    def check_robots(self, robots: int) -> None:
        """ConfigError (one line) unless 1 <= `robots` <= `max_robots`."""
        if robots < 1:
            raise ConfigError(f"--robots must be at least 1 (got {robots})")
        if robots > self.max_robots:
            raise ConfigError(
                f"--robots {robots} is more than team.max_robots ({self.max_robots}); "
                f"--set team.max_robots=N raises the cap"
            )


@dataclass(frozen=True)
class ExplorationConfig(Checked):
    """The whole configuration of one exploration episode."""

    steps: int = ranged(1000, 1, text="at least 1")
    # end the run once G's IoU reaches this level (the authors' IoU-stop protocol); None: never
    until_iou: float | None = ranged(None, 0, 1, low_open=True)
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
    try:
        return dataclasses.replace(node, **{name: value})
    except ConfigError:
        raise
    except (TypeError, ValueError) as error:  # a dataclass's own check that is not a ConfigError
        raise ConfigError(f"override '{item}': {' '.join(str(error).split())}") from None


def _coerce(raw: str, hint: Any, item: str) -> Any:
    if dataclasses.is_dataclass(hint):
        fields = ", ".join(f"{item.partition('=')[0]}.{f.name}" for f in dataclasses.fields(hint))
        raise ConfigError(f"override '{item}': a section takes no value; set its fields ({fields})")
    origin = typing.get_origin(hint)
    if origin is Literal:
        if raw not in typing.get_args(hint):
            raise ConfigError(f"override '{item}': choose one of {typing.get_args(hint)}")
        return raw
    if origin in (typing.Union, types.UnionType):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    if typing.get_origin(hint) is tuple:  # tuple[X, ...] or tuple[X, Y]: comma-separated values
        parts = [part.strip() for part in raw.split(",")]
        hints = typing.get_args(hint)
        if len(hints) == 2 and hints[1] is Ellipsis:
            hints = hints[:1] * len(parts)
        elif len(hints) != len(parts):
            raise ConfigError(f"override '{item}': give {len(hints)} comma-separated values")
        return tuple(_coerce(part, each, item) for part, each in zip(parts, hints, strict=True))
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


def add_override_argument(
    parser: argparse.ArgumentParser,
    help: str = "override a configuration field, e.g. visibility.stop_rule=accumulate (repeatable)",
) -> None:
    """--set SECTION.FIELD=VALUE (repeatable) into `args.overrides` (see `apply_overrides`)."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help=help,
    )
