"""The time budget: `--steps auto` by floor area, reproducing the authors' size classes, and
the one-line errors of --steps and --until-iou."""

import pytest

from mapex.budget import auto_steps, parse_level, parse_steps, resolve_steps, steps_for_area
from mapex.worlds import generate_floor_plan

# the authors' 14 KTH test floors (pipe-planner kth_test_maps): valid area in m2 at this
# project's raster (their rasters are twice as fine), and the class explore.py gives them
AUTHORS_FLOORS = {
    "50010535_PLAN1": (2696, 3000),
    "50010535_PLAN2": (2853, 3000),
    "50010536_PLAN3": (2053, 3000),
    "50015847": (4851, 6000),
    "50015848": (4501, 6000),
    "50037764_PLAN1": (1784, 3000),
    "50037765_PLAN3": (1576, 3000),
    "50052748": (666, 3000),
    "50052749": (1080, 1500),
    "50052750": (1105, 1500),
    "50052751": (450, 3000),
    "50052752": (449, 3000),
    "50052753": (448, 3000),
    "50052754": (452, 3000),
}


def test_the_size_rule_reproduces_twelve_of_the_authors_fourteen_classes():
    missed = sorted(
        name for name, (area, steps) in AUTHORS_FLOORS.items() if steps_for_area(area) != steps
    )
    # explore.py calls 2749 / 2750 small although four floors of less than half their area
    # are medium: no rule monotone in size can; they get the medium budget (more steps)
    assert missed == ["50052749", "50052750"]
    assert all(steps_for_area(AUTHORS_FLOORS[name][0]) == 3000 for name in missed)


def test_auto_resolves_per_world_and_a_number_is_kept():
    world = generate_floor_plan(3)
    assert resolve_steps(None, world) == auto_steps(world) in (1500, 3000, 6000)
    assert resolve_steps(250, world) == 250
    assert steps_for_area(0.0) == 1500 and steps_for_area(1e9) == 6000


@pytest.mark.parametrize(
    ("text", "message"),
    [("0", "at least 1"), ("-5", "at least 1"), ("1.5", "whole number or 'auto'"), ("", "whole")],
)
def test_bad_steps_are_one_line_errors(text, message):
    with pytest.raises(ValueError, match=message):
        parse_steps(text)


def test_steps_parse():
    assert parse_steps("auto") is None and parse_steps(" AUTO ") is None
    assert parse_steps("1000") == 1000


@pytest.mark.parametrize("text", ["0", "-0.1", "1.01", "nan", "x", "inf"])
def test_bad_levels_are_one_line_errors(text):
    with pytest.raises(ValueError, match="--until-iou must be"):
        parse_level(text)


def test_levels_parse():
    assert parse_level("0.95") == 0.95 and parse_level("1") == 1.0
