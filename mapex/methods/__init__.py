"""The exploration methods of docs/algorithms.md#methods (the paper's eight, three of our
own and the authors' follow-up PIPE with its baseline), selectable by name."""

from __future__ import annotations

from collections.abc import Collection

from mapex.config import ExplorationConfig
from mapex.methods.base import FrontierScorer, Method, PlanningContext
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
    )
}
MAIN_COMPARISON = ("nearest", "upen", "ig_hector", "mapex")
ABLATIONS = ("deterministic", "no_variance", "observed_map", "no_visibility")
BEYOND_PAPER = ("mapex_path", "mapex_plus", "mapex_plus_observed")  # ours (docs/algorithms.md)
FOLLOW_UP = ("pipe", "pw_nbv")  # the authors' IROS 2025 follow-up (docs/algorithms.md#pipe)


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
    "FrontierScorer",
    "Method",
    "PlanningContext",
    "make_method",
    "parse_method_list",
]
