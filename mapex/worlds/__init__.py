"""Ground-truth worlds (docs/algorithms.md#worlds): KTH map directories, procedural floor plans,
HouseExpo houses, start poses.

`load_world` turns a world spec into a World, dispatching through `WORLD_SOURCES`
(mapex/worlds/sources.py): "default" (the embedded default world, DEFAULT_WORLD),
"generated:<seed>", "generated-open:<seed>" (the same plan with free space around the
building, as in the KTH maps), "houseexpo:<index>" (one HouseExpo house),
"houseexpo-corridor:<seed>" (HouseExpo houses along a corridor) or the path of a map
directory in the KTH format (KTH and IPA maps). `world_spec_help()` lists them for help
and error texts.
"""

from __future__ import annotations

from mapex.worlds.base import World, WorldError, generated_prefix
from mapex.worlds.kth import load_kth_map
from mapex.worlds.procedural import generate_floor_plan
from mapex.worlds.sources import (
    DEFAULT_SPEC,
    DEFAULT_WORLD,
    WORLD_SOURCES,
    WorldSource,
    load_world,
    register_world_source,
    world_spec_help,
)
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

__all__ = [
    "DEFAULT_SPEC",
    "DEFAULT_WORLD",
    "WORLD_SOURCES",
    "StartSpec",
    "World",
    "WorldError",
    "WorldSource",
    "generate_floor_plan",
    "generated_prefix",
    "load_kth_map",
    "load_world",
    "normalise_start",
    "parse_start",
    "register_world_source",
    "start_argument",
    "start_cell",
    "start_label",
    "start_poses",
    "start_spec_of",
    "world_spec_help",
]
