"""The exploration methods of docs/algorithms.md#methods (the paper's eight, three of our
own, the authors' follow-up PIPE with its baseline, and the team methods of
docs/algorithms.md#teams), selectable by name from one registry."""

from __future__ import annotations

from collections.abc import Collection

from mapex.config import ExplorationConfig
from mapex.methods.assignment import MapExAssign
from mapex.methods.base import FrontierScorer, Method, PlanningContext
from mapex.methods.coordinated import MapExIndependent, MapExPlusTeam, MapExTeam, NearestTeam
from mapex.methods.ig_hector import IgHector
from mapex.methods.information_gain import (
    Deterministic,
    MapEx,
    NoVariance,
    NoVisibility,
    ObservedMap,
)
from mapex.methods.nearest import NearestFrontier
from mapex.methods.path_gain import MapExPath, MapExPlus
from mapex.methods.pathwise import MapExPlusObserved, PathwiseNbv, Pipe
from mapex.methods.regions import MapExVoronoi
from mapex.methods.upen import Upen

METHODS: dict[str, type[Method]] = {
    cls.name: cls
    for cls in (
        NearestFrontier,
        MapEx,
        Deterministic,
        NoVariance,
        ObservedMap,
        NoVisibility,
        IgHector,
        Upen,
        MapExPath,
        MapExPlus,
        MapExPlusObserved,
        Pipe,
        PathwiseNbv,
        MapExTeam,
        MapExPlusTeam,
        NearestTeam,
        MapExIndependent,
        MapExAssign,
        MapExVoronoi,
    )
}
MAIN_COMPARISON = ("nearest", "upen", "ig_hector", "mapex")
ABLATIONS = ("deterministic", "no_variance", "observed_map", "no_visibility")
BEYOND_PAPER = ("mapex_path", "mapex_plus", "mapex_plus_observed")  # ours (docs/algorithms.md)
FOLLOW_UP = ("pipe", "pw_nbv")  # the authors' IROS 2025 follow-up (docs/algorithms.md#pipe)
TEAM_METHODS = tuple(name for name, cls in METHODS.items() if cls.made_for_teams)
# Each method that reads the prediction, and its twin that does not: the same choice rule on
# the observed map alone, so the pair's difference is what the prediction buys the rule.
PREDICTION_TWINS = {"mapex": "observed_map", "pipe": "pw_nbv", "mapex_plus": "mapex_plus_observed"}


def parse_method_list(text: str, known: Collection[str] = METHODS) -> list[str]:
    """Comma-separated method names (of `known`) -> their list; a one-line ValueError naming
    the unknown."""
    names = [item.strip() for item in text.split(",") if item.strip()]
    unknown = [name for name in names if name not in known]
    if unknown or not names:
        raise ValueError(
            f"unknown method {', '.join(unknown) or repr(text)} (choose from {', '.join(known)})"
        )
    return names


def records_team(method: str, robots: int) -> bool:
    """Whether a run's record carries the team's size and fields (its name ends in
    -team<N>): several robots, or a method made for teams (docs/algorithms.md#teams)."""
    return robots > 1 or (method in METHODS and METHODS[method].made_for_teams)


def make_method(name: str, config: ExplorationConfig) -> Method:
    """Instantiate the method called `name` (ValueError with the choices otherwise)."""
    if name not in METHODS:
        raise ValueError(f"unknown method '{name}' (choose from: {', '.join(METHODS)})")
    return METHODS[name](config)


__all__ = [
    "ABLATIONS",
    "BEYOND_PAPER",
    "FOLLOW_UP",
    "MAIN_COMPARISON",
    "METHODS",
    "PREDICTION_TWINS",
    "TEAM_METHODS",
    "FrontierScorer",
    "Method",
    "PlanningContext",
    "make_method",
    "records_team",
    "parse_method_list",
]
