"""World sources: every form of world spec that `load_world` reads (docs/algorithms.md#worlds).

`WORLD_SOURCES` names each source: how a spec of it is recognised (it starts with a prefix,
it is one exact word, it names a file with one of some suffixes, or it is a directory), the
syntax shown to users, a one-line description and its loader as a "module:function" string,
imported only when a spec of that source is loaded (as `mapex.prediction.PREDICTORS` does).
A loader takes the spec's argument (the text after the prefix; the whole spec for a file or
a directory) and returns a World or raises a one-line WorldError; a loader that reads files
may also take `max_cells` (the `world.max_cells` limit), to refuse a file from its header
before reading it. Adding a source is one `register_world_source` call; the `--world` help
of every command and the error for a spec that names no world are built from the registry
(`world_spec_help`), so they list every source.
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from mapex.config import WorldConfig
from mapex.worlds.base import (
    CORRIDOR_PREFIX,
    GENERATED_PREFIX,
    HOUSE_PREFIX,
    KTH_SDF_PREFIX,
    OPEN_GENERATED_PREFIX,
    World,
    WorldError,
)

DEFAULT_WORLD = "generated:0"
DEFAULT_SPEC = "default"
DEFAULT_MAX_CELLS = WorldConfig().max_cells

Match = Literal["prefix", "exact", "suffix", "directory"]


@dataclass(frozen=True)
class WorldSource:
    """One form of world spec.

    match: "prefix" (the spec starts with `key`, the loader gets the rest), "exact" (the
    spec is `key`, the loader gets ""), "suffix" (the spec, up to an `@` that starts its
    options, ends with one of the space-separated suffixes of `key`, e.g. ".world .sdf"; the
    loader gets it whole) or "directory" (the spec is the path of a directory, the loader
    gets it whole; `key` unused). syntax: the form shown to users
    ("generated:SEED"). loader: "module:function", the function taking the argument.
    """

    name: str
    match: Match
    key: str
    syntax: str
    description: str
    loader: str

    def __post_init__(self) -> None:
        if self.match not in ("prefix", "exact", "suffix", "directory"):
            raise ValueError(f"world source '{self.name}': unknown match '{self.match}'")
        if self.match != "directory" and not self.key:
            raise ValueError(f"world source '{self.name}': a {self.match} source needs a key")
        module_name, colon, function_name = self.loader.partition(":")
        if not (module_name and colon and function_name):
            raise ValueError(
                f"world source '{self.name}': loader '{self.loader}' is not 'module:function'"
            )

    def recognises(self, spec: str) -> bool:
        """Whether `spec` is of this source (a directory source: an existing directory)."""
        if self.match == "prefix":
            return spec.startswith(self.key)
        if self.match == "exact":
            return spec == self.key
        if self.match == "suffix":
            return spec.partition("@")[0].lower().endswith(tuple(self.key.split()))
        return Path(spec).is_dir()

    def load(self, spec: str, max_cells: int = DEFAULT_MAX_CELLS) -> World:
        """The world of `spec` (a spec this source recognises); a loader that takes
        `max_cells` gets it (it refuses a bigger map before reading it)."""
        arguments = {
            "prefix": spec[len(self.key) :],
            "exact": "",
            "suffix": spec,
            "directory": spec,
        }
        module_name, _, function_name = self.loader.partition(":")
        loader = getattr(importlib.import_module(module_name), function_name)
        if "max_cells" in inspect.signature(loader).parameters:
            return loader(arguments[self.match], max_cells=max_cells)
        return loader(arguments[self.match])

    def shown(self, described: bool = True) -> str:
        """The syntax as help and errors show it: quoted unless a directory, with its
        description in parentheses when `described`."""
        syntax = self.syntax if self.match in ("directory", "suffix") else f"'{self.syntax}'"
        return f"{syntax} ({self.description})" if described else syntax


WORLD_SOURCES: dict[str, WorldSource] = {}


def register_world_source(source: WorldSource) -> WorldSource:
    """Add `source` to `WORLD_SOURCES` (shown after the sources registered before it).

    ValueError when its name or its key is taken, or for a second directory source.
    """
    for other in WORLD_SOURCES.values():
        if other.name == source.name:
            raise ValueError(f"world source '{source.name}' is already registered")
        if source.match == other.match == "directory":
            raise ValueError(
                f"world source '{source.name}': '{other.name}' already reads directories"
            )
        if source.match != "directory" and other.match == source.match and other.key == source.key:
            raise ValueError(
                f"world source '{source.name}': '{other.name}' already reads '{source.key}'"
            )
    WORLD_SOURCES[source.name] = source
    return source


def world_spec_help(described: bool = True) -> str:
    """Every registered form of world spec in one line, for a `--world` help (with the
    descriptions) or an error (`described=False`): "'default' (...), ... or DIR (...)"."""
    shown = [source.shown(described) for source in _in_help_order()]
    return shown[0] if len(shown) == 1 else ", ".join(shown[:-1]) + " or " + shown[-1]


def find_world_source(spec: str) -> WorldSource | None:
    """The source `spec` is of: an exact word, else the longest matching prefix, else a file
    source whose suffix it has, else the directory source when `spec` is a directory; None
    when it is none of them."""
    exact = [s for s in WORLD_SOURCES.values() if s.match == "exact" and s.recognises(spec)]
    prefixed = [s for s in WORLD_SOURCES.values() if s.match == "prefix" and s.recognises(spec)]
    suffixed = [s for s in WORLD_SOURCES.values() if s.match == "suffix" and s.recognises(spec)]
    if exact:
        return exact[0]
    if prefixed:
        return max(prefixed, key=lambda source: len(source.key))
    if suffixed:
        return suffixed[0]
    directory = _directory_source()
    return directory if directory is not None and directory.recognises(spec) else None


def load_world(spec: str, max_cells: int = DEFAULT_MAX_CELLS) -> World:
    """The world named by `spec`; a one-line WorldError when it names none (the error lists
    every registered form of spec) or has more than `max_cells` cells (the `world.max_cells`
    setting: a map file is refused from its header, before its data is read)."""
    if not spec:
        raise WorldError(f"empty world spec: expected {world_spec_help(described=False)}")
    source = find_world_source(spec)
    if source is None:
        expected = world_spec_help(described=False)
        if _directory_source() is not None:
            raise WorldError(f"no such map directory: {spec} (a world spec is {expected})")
        raise WorldError(f"unknown world spec '{spec}': expected {expected}")
    return source.load(spec, max_cells).check_size(max_cells)


def default_world(_: str = "") -> World:
    """The embedded default world (spec 'default'): DEFAULT_WORLD."""
    return load_world(DEFAULT_WORLD)


def _directory_source() -> WorldSource | None:
    return next((s for s in WORLD_SOURCES.values() if s.match == "directory"), None)


def _in_help_order() -> list[WorldSource]:
    """Registration order, the directory source last (it takes what no other source does)."""
    sources = list(WORLD_SOURCES.values())
    return [s for s in sources if s.match != "directory"] + [
        s for s in sources if s.match == "directory"
    ]


for _source in (
    WorldSource(
        "default",
        "exact",
        DEFAULT_SPEC,
        DEFAULT_SPEC,
        f"the embedded default world, {DEFAULT_WORLD}",
        "mapex.worlds.sources:default_world",
    ),
    WorldSource(
        "generated",
        "prefix",
        GENERATED_PREFIX,
        f"{GENERATED_PREFIX}SEED",
        "a seeded procedural office floor plan",
        "mapex.worlds.procedural:generated_world",
    ),
    WorldSource(
        "generated-open",
        "prefix",
        OPEN_GENERATED_PREFIX,
        f"{OPEN_GENERATED_PREFIX}SEED",
        "the same plan with free space outside the building, as in the KTH maps",
        "mapex.worlds.procedural:open_generated_world",
    ),
    WorldSource(
        "houseexpo",
        "prefix",
        HOUSE_PREFIX,
        f"{HOUSE_PREFIX}INDEX",
        "one HouseExpo house plan",
        "mapex.worlds.houseexpo:house_world_of_spec",
    ),
    WorldSource(
        "houseexpo-corridor",
        "prefix",
        CORRIDOR_PREFIX,
        f"{CORRIDOR_PREFIX}SEED",
        "seeded HouseExpo houses along a corridor",
        "mapex.worlds.houseexpo:corridor_world_of_spec",
    ),
    WorldSource(
        "gazebo",
        "suffix",
        ".world .sdf",
        "FILE.world[@scale=F,frame=drop]",
        "a Gazebo SDF world: static boxes, cylinders and spheres as walls, the inside derived",
        "mapex.worlds.gazebo:load_gazebo_world",
    ),
    WorldSource(
        "kth-sdf",
        "prefix",
        KTH_SDF_PREFIX,
        f"{KTH_SDF_PREFIX}ID",
        "a KTH floor of ../shared/data/kth_sdf at its real size, the converter's frame dropped",
        "mapex.worlds.gazebo:load_kth_sdf_world",
    ),
    WorldSource(
        "kth",
        "directory",
        "",
        "DIR",
        "a map directory in the KTH format, occ_map.npy + valid_space.npy: KTH and IPA maps",
        "mapex.worlds.kth:load_kth_map",
    ),
):
    register_world_source(_source)
