"""The time budget T of a run: a number of steps, or `auto`, chosen from the building's size
as the authors' IoU-stop protocol does (docs/algorithms.md#budget)."""

from __future__ import annotations

import argparse

from mapex.config import argparse_type
from mapex.worlds.base import World

AUTO = "auto"
# (valid floor area in m2 at least, steps), largest first: PIPE's large / medium / small
# budgets (explore.py with log_iou); the size rule puts 12 of their 14 KTH test floors in
# the class explore.py names (docs/algorithms.md#budget)
AUTO_BUDGETS: tuple[tuple[float, int], ...] = ((3_500.0, 6000), (400.0, 3000), (0.0, 1500))

Steps = int | None
"""A budget as asked for: a number of steps, or None for `auto`."""


def parse_steps(text: str) -> Steps:
    """`--steps` text -> steps (>= 1) or None for `auto`; a one-line ValueError otherwise."""
    if text.strip().lower() == AUTO:
        return None
    try:
        steps = int(text)
    except ValueError:
        raise ValueError(f"--steps must be a whole number or 'auto', got {text!r}") from None
    if steps < 1:
        raise ValueError(f"--steps must be at least 1, got {steps}")
    return steps


def floor_area_m2(world: World) -> float:
    """The world's valid (explorable) area in square metres."""
    return float(world.valid_space.sum()) * world.resolution_m**2


def steps_for_area(area_m2: float) -> int:
    """The `auto` budget of a building of `area_m2`: the steps of the first class it reaches."""
    return next(steps for least, steps in AUTO_BUDGETS if area_m2 >= least)


def auto_steps(world: World) -> int:
    """The `auto` budget of `world`, from its valid floor area."""
    return steps_for_area(floor_area_m2(world))


def resolve_steps(steps: Steps, world: World) -> int:
    """The budget in steps for `world`: `steps` itself, or the `auto` budget when None."""
    return auto_steps(world) if steps is None else steps


def steps_text(steps: Steps) -> str:
    """The `--steps` argument that asks for this budget (for spawned processes)."""
    return AUTO if steps is None else str(steps)


def parse_level(text: str) -> float:
    """`--until-iou` text -> a level in (0, 1]; a one-line ValueError otherwise."""
    try:
        level = float(text)
    except ValueError:
        raise ValueError(f"--until-iou must be a number in (0, 1], got {text!r}") from None
    if not 0.0 < level <= 1.0:
        raise ValueError(f"--until-iou must be in (0, 1], got {text}")
    return level


def add_budget_arguments(parser: argparse.ArgumentParser) -> None:
    """--steps T|auto and --until-iou LEVEL (into `args.steps`, `args.until_iou`)."""
    parser.add_argument(
        "--steps",
        type=argparse_type(parse_steps),
        default=1000,
        metavar="T|auto",
        help="time budget T in steps, or 'auto': 6000 / 3000 / 1500 by the building's floor "
        "area (docs/algorithms.md#budget); default: %(default)s",
    )
    parser.add_argument(
        "--until-iou",
        type=argparse_type(parse_level),
        default=None,
        metavar="LEVEL",
        help="end a run once G's IoU reaches LEVEL, e.g. 0.95 (checked at every metric "
        "sample; the authors' IoU-stop protocol); default: run to T",
    )
