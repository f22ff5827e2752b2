"""`python -m mapex.report.radius`: how far a team's speed-up could go on each map.

For every world and team size in the results, the radius bound (`mapex.reach_bound`: the
first step at which any team from those starts could reach the coverage level) against one
reference robot's median steps: a team of N robots can be at most min(N, one robot's
median / bound) times faster than that robot (Brass et al., T-RO 2011: k-fold, and the
radius), next to the speed-ups measured. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mapex.reach_bound import radius_bound_steps
from mapex.report.config import ReportConfig
from mapex.report.runs import ReportError, RunRecord, load_folders
from mapex.report.speedup import (
    COVERAGE,
    NO_DATA,
    Interval,
    censored_median,
    group_of,
    ratio,
    speedup_rows,
)
from mapex.report.tables import markdown_table
from mapex.worlds import World, WorldError, load_world


@dataclass(frozen=True)
class RadiusRow:
    """One world (or "pooled") and team size: the bound and what it leaves a team."""

    world: str
    robots: int
    episodes: int
    bound_steps: float  # median over episodes of the radius bound (steps)
    reference_steps: Interval  # one reference robot's median steps on those episodes
    ceiling: Interval  # min(N, reference / bound)
    measured: dict[str, Interval]  # team method -> its speed-up on this world


def run_starts(run: RunRecord) -> list[tuple[int, int]]:
    """Every robot's start cell of a run (one for a robot alone)."""
    team = run.metrics.get("team") or {}
    starts = team.get("starts") or [run.metrics["start"]]
    return [(int(r), int(c)) for r, c in starts]


def run_bound(run: RunRecord, world: World, level: float) -> int | None:
    """The radius bound of a run's starts, with the sensor and motion it ran with."""
    config = run.metrics.get("config") or {}
    range_cells = int(config["sensor"]["range_cells"])
    cells_per_step = int(config["motion"]["cells_per_step"])
    bounds = radius_bound_steps(
        world.occupancy, world.valid_space, run_starts(run), [level], range_cells, cells_per_step
    )
    return bounds[level]


def radius_rows(
    runs: Sequence[RunRecord], worlds: dict[str, World], config: ReportConfig
) -> list[RadiusRow]:
    """One row per (world, team size), then per team size over every world ("pooled")."""
    level = config.speedup_level
    reference = [r for r in runs if group_of(r) == (config.speedup_reference, 1)]
    bounds: dict[tuple[str, int], dict[tuple, int | None]] = {}
    for run in runs:
        if run.world not in worlds:
            raise ReportError(f"no map given for world {run.world}: add it to --maps")
        episodes = bounds.setdefault((run.world, group_of(run)[1]), {})
        key = (run.world, run.start, run.seed)
        if key not in episodes:
            episodes[key] = run_bound(run, worlds[run.world], level)
    measured = {(row.method, row.robots): row for row in speedup_rows(runs, config)}
    rows = []
    sizes = sorted({n for _, n in bounds})
    for world in [*sorted({w for w, _ in bounds}), "pooled"]:
        for robots in sizes:
            episodes = {
                key: bound
                for (w, n), found in bounds.items()
                if n == robots and world in (w, "pooled")
                for key, bound in found.items()
            }
            if not episodes:
                continue
            one = [r for r in reference if (r.world, r.start, r.seed) in episodes]
            rows.append(_row(world, robots, episodes, one, measured, level))
    return rows


def _row(
    world: str,
    robots: int,
    episodes: dict[tuple, int | None],
    one: list[RunRecord],
    measured: dict,
    level: float,
) -> RadiusRow:
    bound = statistics.median(math.inf if b is None else float(b) for b in episodes.values())
    reference = censored_median(
        [r.reached(COVERAGE, level) for r in one], [int(r.metrics["steps"]) for r in one]
    ) if one else NO_DATA  # fmt: skip
    ceiling = (
        ratio(reference, Interval(bound, bound)) if bound > 0 else Interval(math.inf, math.inf)
    )
    ceiling = (
        Interval(min(robots, ceiling.low), min(robots, ceiling.high)) if ceiling.known else ceiling
    )
    teams = {
        f"{method} x{n}": (row.speedup if world == "pooled" else row.by_world.get(world, NO_DATA))
        for (method, n), row in measured.items()
        if n == robots and n > 1
    }
    return RadiusRow(world, robots, len(episodes), bound, reference, ceiling, teams)


def radius_markdown(rows: Sequence[RadiusRow], config: ReportConfig) -> str:
    """The table: world, N, episodes, bound, one robot's median, ceiling, measured."""
    level = f"{config.speedup_level * 100:g} %"
    header = [
        "world", "robots", "episodes", f"radius bound to {level} (steps, median)",
        f"one `{config.speedup_reference}` robot (steps, median)", "ceiling min(N, one / bound)",
        "measured speed-ups",
    ]  # fmt: skip
    body = [
        [
            row.world, row.robots, row.episodes, f"{row.bound_steps:.0f}",
            row.reference_steps.text(), row.ceiling.text(2),
            ", ".join(f"{name} {value.text(2)}" for name, value in row.measured.items()) or "–",
        ]
        for row in rows
    ]  # fmt: skip
    return markdown_table(header, body)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mapex.report.radius", description=__doc__)
    parser.add_argument("results", nargs="+", type=Path, metavar="RESULTS_DIR")
    parser.add_argument(
        "--maps", nargs="+", required=True, help="the world specs the runs ran on (map folders)"
    )
    args = parser.parse_args(argv)
    config = ReportConfig()
    try:
        for folder in args.results:
            if not folder.is_dir():
                raise ReportError(f"{folder} is not a folder of runs")
        runs = load_folders(args.results)
        if not runs:
            raise ReportError("no finished runs in " + ", ".join(map(str, args.results)))
        worlds = {world.name: world for world in map(load_world, args.maps)}
        print(radius_markdown(radius_rows(runs, worlds, config), config))
    except (ReportError, WorldError, KeyError, ValueError) as error:
        print(f"mapex.report.radius: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
