"""World sources: the registry `load_world` dispatches through, and the texts built from it."""

from __future__ import annotations

import contextlib
import importlib
import io
from pathlib import Path

import numpy as np
import pytest
from sdf_worlds import model, room_links, world, write

from mapex.worlds import (
    WORLD_SOURCES,
    World,
    WorldError,
    WorldSource,
    generate_floor_plan,
    load_kth_map,
    load_world,
    register_world_source,
    world_spec_help,
)
from mapex.worlds.data import HOUSEEXPO_PLANS, KTH_SDF_DIR
from mapex.worlds.gazebo import GazeboOptions, gazebo_world
from mapex.worlds.houseexpo import corridor_world, house_world
from mapex.worlds.procedural import plan_config

NEEDS_HOUSEEXPO = pytest.mark.skipif(
    not HOUSEEXPO_PLANS.is_file(), reason="../shared/data/houseexpo is not present"
)
NEEDS_KTH_SDF = pytest.mark.skipif(
    not KTH_SDF_DIR.is_dir(), reason="../shared/data/kth_sdf is not present"
)
DEV_MAP = "50052748"  # the smallest development map
SDF_WORLD = world(model("m", "0 0 0 0 0 0", room_links(6, 4)))  # a hand-made Gazebo world


def sample_spec(name: str, kth_dir: Path | None, tmp_dir: Path | None = None) -> str:
    """A spec of each built-in source (`kth_dir`: the development maps, for "kth"; `tmp_dir`:
    where the "gazebo" sample is written)."""
    if name == "gazebo":
        return f"{write(tmp_dir / 'room.world', SDF_WORLD)}@scale=0.5"
    return {
        "default": "default",
        "generated": "generated:3",
        "generated-open": "generated-open:3",
        "houseexpo": "houseexpo:0",
        "houseexpo-corridor": "houseexpo-corridor:0",
        "kth-sdf": f"kth-sdf:{DEV_MAP}",
        "kth": str(kth_dir / DEV_MAP) if kth_dir else "unused",
    }[name]


def expected_world(name: str, kth_dir: Path | None, tmp_dir: Path | None = None) -> World:
    """The world `sample_spec(name)` loaded before the registry, by the same functions."""
    options = GazeboOptions(scale=0.5, drop_frame=True)
    return {
        "gazebo": lambda: gazebo_world(tmp_dir / "room.world", GazeboOptions(scale=0.5)),
        "kth-sdf": lambda: gazebo_world(KTH_SDF_DIR / "check" / f"{DEV_MAP}.world", options),
        "default": lambda: generate_floor_plan(0),
        "generated": lambda: generate_floor_plan(3, plan_config(free_outside=False)),
        "generated-open": lambda: generate_floor_plan(3, plan_config(free_outside=True)),
        "houseexpo": lambda: house_world(0),
        "houseexpo-corridor": lambda: corridor_world(0),
        "kth": lambda: load_kth_map(kth_dir / DEV_MAP),
    }[name]()


BUILT_IN = {
    "default": [],
    "generated": [],
    "generated-open": [],
    "houseexpo": [NEEDS_HOUSEEXPO],
    "houseexpo-corridor": [NEEDS_HOUSEEXPO],
    "gazebo": [],
    "kth-sdf": [NEEDS_KTH_SDF],
    "kth": [],
}


@pytest.fixture
def scratch_registry():
    """WORLD_SOURCES as it was, restored after the test (which may register sources)."""
    saved = dict(WORLD_SOURCES)
    yield WORLD_SOURCES
    WORLD_SOURCES.clear()
    WORLD_SOURCES.update(saved)


def test_every_registered_source_has_a_sample_here() -> None:
    assert list(WORLD_SOURCES) == list(BUILT_IN)


@pytest.mark.parametrize(
    "name", [pytest.param(name, marks=marks) for name, marks in BUILT_IN.items()]
)
def test_every_source_loads_its_sample_spec(
    name: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    kth_dir = request.getfixturevalue("kth_dev_dir") if name == "kth" else None
    world = load_world(sample_spec(name, kth_dir, tmp_path))
    expected = expected_world(name, kth_dir, tmp_path)
    assert world.name == expected.name
    assert np.array_equal(world.occupancy, expected.occupancy)
    assert np.array_equal(world.valid_space, expected.valid_space)


def test_world_names_are_unchanged() -> None:
    assert load_world("default").name == "generated:0"
    assert load_world("generated:2").name == "generated:2"
    assert load_world("generated-open:2").name == "generated-open:2"


@pytest.mark.parametrize("spec", ["nope", "genrated:3", "defaults", "/no/such/dir", ""])
def test_an_unknown_spec_is_one_line_listing_every_source(spec: str) -> None:
    with pytest.raises(WorldError) as caught:
        load_world(spec)
    message = str(caught.value)
    assert "\n" not in message
    for source in WORLD_SOURCES.values():
        assert source.shown(described=False) in message
    expected = "empty world spec" if not spec else f"no such map directory: {spec}"
    assert message.startswith(expected)


def test_help_names_every_source_with_its_description() -> None:
    text = world_spec_help()
    for source in WORLD_SOURCES.values():
        assert source.syntax in text and source.description in text
    assert text.endswith("or " + WORLD_SOURCES["kth"].shown())  # the directory comes last


def test_a_registered_source_loads_and_is_listed(scratch_registry) -> None:
    register_world_source(
        WorldSource(
            "tiny",
            "prefix",
            "tiny:",
            "tiny:SEED",
            "a test world",
            "mapex.worlds.procedural:generated_world",
        )
    )
    assert load_world("tiny:4").name == "generated:4"
    assert "'tiny:SEED' (a test world)" in world_spec_help()
    with pytest.raises(WorldError, match="'tiny:SEED'"):
        load_world("tinny:4")


def test_the_longest_prefix_wins(scratch_registry) -> None:
    register_world_source(
        WorldSource(
            "generated-big",
            "prefix",
            "generated:big:",
            "generated:big:SEED",
            "shadows generated:",
            "mapex.worlds.procedural:open_generated_world",
        )
    )
    assert load_world("generated:big:2").name == "generated-open:2"
    assert load_world("generated:2").name == "generated:2"


@pytest.mark.parametrize(
    "source, message",
    [
        (WorldSource("generated", "prefix", "x:", "x:N", "d", "m:f"), "already registered"),
        (WorldSource("x", "prefix", "generated:", "x:N", "d", "m:f"), "already reads"),
        (WorldSource("x", "directory", "", "DIR", "d", "m:f"), "already reads directories"),
    ],
)
def test_clashing_sources_are_refused(scratch_registry, source, message) -> None:
    with pytest.raises(ValueError, match=message):
        register_world_source(source)


@pytest.mark.parametrize(
    "fields, message",
    [
        (("x", "regex", "x:", "x:N", "d", "m:f"), "unknown match"),
        (("x", "prefix", "", "x:N", "d", "m:f"), "needs a key"),
        (("x", "prefix", "x:", "x:N", "d", "module.function"), "not 'module:function'"),
    ],
)
def test_malformed_sources_are_refused(fields, message) -> None:
    with pytest.raises(ValueError, match=message):
        WorldSource(*fields)


def run_subcommand_help(module: str) -> str:
    parser = importlib.import_module(module).build_parser()
    if module == "mapex.cli":  # `python -m mapex run --world ...`
        (commands,) = (a for a in parser._actions if a.dest == "command")
        parser = commands.choices["run"]
    return parser.format_help()


def main_help(module: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        importlib.import_module(module).main(["--help"])
    return out.getvalue()


@pytest.mark.parametrize(
    "module, help_of",
    [
        ("mapex.cli", run_subcommand_help),
        ("mapex.audit", run_subcommand_help),
        ("mapex.bench", main_help),
        ("services.world", run_subcommand_help),
        ("services.planner", run_subcommand_help),
        ("services.up", run_subcommand_help),
        ("services.evaluate", run_subcommand_help),
        ("services.bench", main_help),
    ],
)
def test_world_help_of_every_command_lists_every_source(
    module, help_of, scratch_registry, monkeypatch
) -> None:
    register_world_source(  # built from the registry at parse time, not written out
        WorldSource("late", "prefix", "late:", "late:N", "registered late", "m:f")
    )
    monkeypatch.setenv("COLUMNS", "100000")  # no wrapping inside a source's text
    text = help_of(module)
    for source in WORLD_SOURCES.values():
        assert source.shown() in text, (module, source.name)
