"""Every tunable number of the system, in one typed place.

Defaults follow ../shared/SPEC.md (units: cells of 0.1 m, steps of the episode).
Any field can be overridden from the command line as `section.field=value`
(see `apply_overrides`), e.g. `--set visibility.stop_rule=threshold`.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Literal

StopRule = Literal["accumulate", "threshold"]


@dataclass(frozen=True)
class SensorConfig:
    """The 2D LiDAR of SPEC §2."""

    n_rays: int = 2500
    range_cells: int = 200  # 20 m


@dataclass(frozen=True)
class MotionConfig:
    """Robot motion per timestep (SPEC §2)."""

    cells_per_step: int = 3


@dataclass(frozen=True)
class FrontierConfig:
    """Frontier clustering (SPEC §3): clusters of `max_dropped_cluster_cells` or fewer go."""

    max_dropped_cluster_cells: int = 10


@dataclass(frozen=True)
class NavigationConfig:
    """Planning cost map, A* and the goal-keeping rule (SPEC §2-3)."""

    wall_inflation_cells: int = 1  # 3x3 inflation of known walls
    wall_clearance_cells: float = 5.0  # distance-transform cost fades out at this distance
    wall_cost_weight: float = 2.0  # extra cost per cell at the wall, linearly less to 0
    goal_reached_cells: float = 10.0  # 1 m
    goal_unknown_radius_cells: float = 10.0  # goal dropped when no unknown cell within 1 m


@dataclass(frozen=True)
class VisibilityConfig:
    """Frontier visibility raycasts of SPEC §5."""

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
class MetricsConfig:
    """Metrics of SPEC §6."""

    sample_every_steps: int = 50
    tu_every_steps: int = 100
    tu_goals: int = 100
    footprint_margin_cells: int = 3
    prediction_threshold: float = 0.5


@dataclass(frozen=True)
class WorldConfig:
    """Start poses (SPEC §1)."""

    start_clearance_cells: int = 3  # 0.3 m


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
    try:
        if hint is bool:
            if raw.lower() not in ("true", "false", "1", "0"):
                raise ValueError
            return raw.lower() in ("true", "1")
        return hint(raw)
    except (TypeError, ValueError):
        raise ConfigError(f"override '{item}': '{raw}' is not a valid {hint.__name__}") from None
