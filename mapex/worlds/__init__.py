"""Ground-truth worlds (docs/algorithms.md#worlds): KTH map directories, procedural floor plans,
start poses.

`load_world` turns a world spec into a World: "generated:<seed>", "generated-open:<seed>"
(the same plan with free space around the building, as in the KTH maps), "houseexpo:<index>"
(one HouseExpo house), "houseexpo-corridor:<seed>" (HouseExpo houses along a corridor),
"default" (the embedded default world, DEFAULT_WORLD) or the path of a map directory in the
KTH format (KTH and IPA maps).
"""

from __future__ import annotations

from mapex.worlds.base import (
    CORRIDOR_PREFIX,
    HOUSE_PREFIX,
    World,
    WorldError,
    generated_prefix,
)
from mapex.worlds.houseexpo import corridor_world, house_world
from mapex.worlds.kth import load_kth_map
from mapex.worlds.procedural import generate_floor_plan, plan_config
from mapex.worlds.starts import (
    StartSpec,
    normalise_start,
    parse_start,
    start_argument,
    start_cell,
    start_label,
    start_poses,
    start_spec_of,
)

DEFAULT_WORLD = "generated:0"
DEFAULT_SPEC = "default"

__all__ = [
    "DEFAULT_WORLD",
    "StartSpec",
    "World",
    "WorldError",
    "generate_floor_plan",
    "generated_prefix",
    "load_kth_map",
    "load_world",
    "normalise_start",
    "parse_start",
    "start_argument",
    "start_cell",
    "start_label",
    "start_poses",
    "start_spec_of",
]


def load_world(spec: str) -> World:
    """The world named by `spec`; a one-line WorldError when it names none."""
    if not spec:
        raise WorldError(
            "empty world spec: expected 'default', 'generated:<seed>', "
            "'generated-open:<seed>', 'houseexpo:<index>', 'houseexpo-corridor:<seed>' "
            "or a directory"
        )
    if spec == DEFAULT_SPEC:
        spec = DEFAULT_WORLD
    for free_outside in (False, True):
        prefix = generated_prefix(free_outside)
        if spec.startswith(prefix):
            seed = _parse_seed(spec[len(prefix) :])
            return generate_floor_plan(seed, plan_config(free_outside))
    if spec.startswith(HOUSE_PREFIX):
        return house_world(_parse_seed(spec[len(HOUSE_PREFIX) :], "HouseExpo plan index"))
    if spec.startswith(CORRIDOR_PREFIX):
        return corridor_world(_parse_seed(spec[len(CORRIDOR_PREFIX) :]))
    return load_kth_map(spec)


def _parse_seed(text: str, what: str = "generated seed") -> int:
    if not (text.isascii() and text.isdigit()):
        raise WorldError(f"bad {what} '{text}': expected a non-negative integer")
    return int(text)
