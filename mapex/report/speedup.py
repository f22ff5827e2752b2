"""What a team buys in time (docs/algorithms.md#teams): the speed-up of N robots over one.

The speed-up of a team method with N robots is the median first step at which one robot of
the reference method (`ReportConfig.speedup_reference`, `mapex`) reached the coverage level
(`speedup_level`, 90 %) divided by the team's median, both over the same episodes (world,
start, seed), per world and pooled. Brass et al. (T-RO 2011) bound it by N.

Censoring: a run that never reached the level (within its budget T, or before it ran out of
frontiers) took longer than T, at least. A median is then known only as an interval: its
lower end is the median with every such run at its budget, its upper end the median with
every such run at infinity. Both are the same number unless the middle run(s) never got
there: then the median is a bound, "> x" (x counts the censored middle runs at T; for an
even count the mean of the two middle runs). A speed-up of two such medians is the interval
of their ratios: "> x" when only one robot's median is a bound, "< y" when only the team's
is, "?" when both are. Beside it, the median over episodes of each episode's ratio (an
interval the same way), which does not mix the sizes of different buildings as pooled
medians do. speedup.png plots the pooled speed-ups against N with the k-fold
line y = N (bounds as triangles pointing the way the value lies).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mapex.report.config import ReportConfig  # noqa: E402
from mapex.report.runs import RunRecord  # noqa: E402
from mapex.report.tables import markdown_table, order_methods  # noqa: E402

SPEEDUP_FIGURE = "speedup.png"
COVERAGE = "coverage"
Episode = tuple[str, str, int]  # (world, start, seed)
Group = tuple[str, int]  # (method, robots)


@dataclass(frozen=True)
class Interval:
    """A number known to lie in [low, high] (equal: known exactly; NaN: no data)."""

    low: float
    high: float

    @property
    def exact(self) -> bool:
        return self.low == self.high

    @property
    def known(self) -> bool:
        return not (math.isnan(self.low) or math.isnan(self.high))

    def text(self, digits: int = 0) -> str:
        """ "812", "> 1000", "< 1.50", "1.2–1.4", "?" (nothing known) or "–" (no data)."""
        if not self.known:
            return "–"
        if self.exact:
            return f"{self.low:.{digits}f}"
        if math.isinf(self.high):
            return "?" if self.low == 0 else f"> {self.low:.{digits}f}"
        if self.low == 0:
            return f"< {self.high:.{digits}f}"
        return f"{self.low:.{digits}f}–{self.high:.{digits}f}"

    def json(self) -> dict:
        """{"low", "high"} with null for NaN and infinity."""
        return {key: None if not math.isfinite(v) else v for key, v in
                (("low", self.low), ("high", self.high))}  # fmt: skip


NO_DATA = Interval(math.nan, math.nan)


def censored_median(steps: Sequence[int | None], budgets: Sequence[int]) -> Interval:
    """The median of first steps (None: never, within that run's budget) as an interval
    (module doc); NO_DATA for no runs."""
    if not steps:
        return NO_DATA
    at_budget = [float(b) if s is None else float(s) for s, b in zip(steps, budgets, strict=True)]
    never_later = [math.inf if s is None else float(s) for s in steps]
    return Interval(_median(at_budget), _median(never_later))


def _median(values: list[float]) -> float:
    ordered = sorted(values)
    middle = len(ordered) // 2
    if len(ordered) % 2:
        return ordered[middle]
    return (ordered[middle - 1] + ordered[middle]) / 2


def ratio(one: Interval, team: Interval) -> Interval:
    """one / team for two intervals of positive steps (module doc)."""
    if not (one.known and team.known):
        return NO_DATA
    return Interval(_divide(one.low, team.high), _divide(one.high, team.low))


def _divide(a: float, b: float) -> float:
    if b == 0:
        return math.inf if a > 0 else math.nan
    return a / b  # a / inf = 0: nothing known below


def group_of(run: RunRecord) -> Group:
    """(method, robots): a single robot's run is a team of one; the method with its
    predictor when not the default (`mapex@oracle`)."""
    team = run.metrics.get("team") or {}
    return run.labelled_method, int(team.get("robots", 1))


def episode_of(run: RunRecord) -> Episode:
    return run.world, run.start, run.seed


@dataclass(frozen=True)
class SpeedupRow:
    """A team method with N robots against one reference robot on the same episodes."""

    method: str
    robots: int
    episodes: int
    median_steps: dict[float, Interval]  # coverage level -> the team's median first step
    reference_steps: dict[float, Interval]  # the same for one reference robot
    speedup: Interval  # at the configured level
    # median over episodes of one robot's steps / the team's on that episode: scale-free
    # where pooled medians mix buildings of different sizes
    episode_speedup: Interval
    by_world: dict[str, Interval]  # the speed-up on each world's episodes
    path_length_m: float  # the team's path, summed over robots, mean over runs
    idle_steps: float  # per robot, mean over robots and runs
    overlap: float  # mean over runs (NaN for a robot alone)


def team_speedup_rows(runs: Sequence[RunRecord], config: ReportConfig) -> list[SpeedupRow]:
    """`speedup_rows` when they hold a team (more than the reference robot), else none."""
    rows = speedup_rows(runs, config)
    reference = (config.speedup_reference, 1)
    return rows if any((row.method, row.robots) != reference for row in rows) else []


def coverage_levels(runs: Sequence[RunRecord]) -> list[float]:
    """The coverage levels whose first step every run recorded, ascending."""
    common = None
    for run in runs:
        levels = {level for metric, level in run.reach_levels() if metric == COVERAGE}
        common = levels if common is None else common & levels
    return sorted(common or ())


def speedup_rows(runs: Sequence[RunRecord], config: ReportConfig) -> list[SpeedupRow]:
    """One row per (method, robots) with runs on episodes the reference robot also ran, the
    reference itself first (its speed-up is 1); empty without reference runs."""
    reference: Group = (config.speedup_reference, 1)
    groups: dict[Group, dict[Episode, RunRecord]] = {}
    for run in runs:
        groups.setdefault(group_of(run), {})[episode_of(run)] = run
    if reference not in groups:
        return []
    alone = groups[reference]
    levels = coverage_levels(runs)
    if config.speedup_level not in levels:
        return []
    methods = order_methods({m for m, _ in groups}, (config.speedup_reference,))
    rows = []
    for method in methods:
        for robots in sorted(n for m, n in groups if m == method):
            mine = groups[(method, robots)]
            shared = sorted(mine.keys() & alone.keys())
            if shared:
                pairs = [(alone[e], mine[e]) for e in shared]
                row = _row(method, robots, pairs, levels, config.speedup_level)
                if (method, robots) == reference:  # itself: 1 by definition, censored or not
                    one = Interval(1.0, 1.0)
                    row = replace(
                        row,
                        speedup=one,
                        episode_speedup=one,
                        by_world=dict.fromkeys(row.by_world, one),
                    )
                rows.append(row)
    return rows


def _row(
    method: str,
    robots: int,
    pairs: list[tuple[RunRecord, RunRecord]],
    levels: list[float],
    level: float,
) -> SpeedupRow:
    one = [a for a, _ in pairs]
    team = [b for _, b in pairs]
    worlds = sorted({run.world for run in team})
    by_world = {
        world: ratio(_median_of([a for a in one if a.world == world], level),
                     _median_of([b for b in team if b.world == world], level))
        for world in worlds
    }  # fmt: skip
    idle = [v for run in team for v in (run.metrics.get("idle_steps") or [])]
    lengths = [run.metrics.get("path_length_m") for run in team]
    overlaps = [(run.metrics.get("team") or {}).get("overlap") for run in team]
    return SpeedupRow(
        method=method,
        robots=robots,
        episodes=len(pairs),
        median_steps={x: _median_of(team, x) for x in levels},
        reference_steps={x: _median_of(one, x) for x in levels},
        speedup=ratio(_median_of(one, level), _median_of(team, level)),
        episode_speedup=episode_median_speedup(pairs, level),
        by_world=by_world,
        path_length_m=_mean([v for v in lengths if v is not None]),
        idle_steps=_mean(idle),
        overlap=_mean([v for v in overlaps if v is not None]),
    )


def episode_median_speedup(pairs: Sequence[tuple[RunRecord, RunRecord]], level: float) -> Interval:
    """The median over episodes of one robot's first step at `level` / the team's, each
    episode's ratio an interval when a run never got there (module doc); its ends are the
    medians of the episodes' low and high ends."""
    ratios = [ratio(_median_of([one], level), _median_of([team], level)) for one, team in pairs]
    if not ratios:
        return NO_DATA
    return Interval(_median([r.low for r in ratios]), _median([r.high for r in ratios]))


def _median_of(runs: Sequence[RunRecord], level: float) -> Interval:
    steps = [run.reached(COVERAGE, level) for run in runs]
    return censored_median(steps, [int(run.metrics["steps"]) for run in runs])


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else math.nan


# ---------------------------------------------------------------- markdown / json / figure


def _fmt(value: float, digits: int) -> str:
    return f"{value:.{digits}f}" if math.isfinite(value) else "–"


def speedup_markdown(rows: Sequence[SpeedupRow], config: ReportConfig) -> str:
    """The speed-up section: pooled table, then the speed-up per world."""
    level = f"{config.speedup_level * 100:g} %"
    levels = list(rows[0].median_steps)
    header = ["method", "robots", "episodes"]
    header += [f"steps to {x * 100:g} %" for x in levels]
    header += [
        f"speed-up at {level}",
        "median per-episode speed-up",
        "team path (m)",
        "idle steps per robot",
        "overlap",
    ]
    body = []
    for row in rows:
        body.append([
            row.method, row.robots, row.episodes,
            *(row.median_steps[x].text() for x in levels),
            row.speedup.text(2), row.episode_speedup.text(2), _fmt(row.path_length_m, 0),
            _fmt(row.idle_steps, 0), _fmt(row.overlap, 3),
        ])  # fmt: skip
    worlds = sorted({w for row in rows for w in row.by_world})
    teams = [row for row in rows if (row.method, row.robots) != (config.speedup_reference, 1)]
    per_world = markdown_table(
        ["world", *(f"{row.method} x{row.robots}" for row in teams)],
        [[world, *(row.by_world.get(world, NO_DATA).text(2) for row in teams)] for world in worlds],
    )
    return "\n\n".join([
        "### Speed-up over one robot",
        f"Median first step at which the team's coverage reached each level, over the "
        f"episodes (world, start, seed) that one `{config.speedup_reference}` robot also ran; "
        f"speed-up: one robot's median steps to {level} / the team's (the k-fold bound is N). "
        "A run that never reached a level counts as later than its budget T: a median that "
        "falls on such runs is a bound (`> x`, with them at T), and so is a speed-up made "
        "of one (`> x`: one robot's median is a bound; `< y`: the team's; `?`: both). The "
        "median per-episode speed-up is the median over episodes of one robot's steps / the "
        "team's on that episode (scale-free where pooled medians mix buildings of different "
        "sizes; an episode's ratio is a bound when a run never got there). Team "
        "path: every robot's path summed; idle steps: steps a robot stood still while the "
        "run went on.",
        markdown_table(header, body),
        f"Speed-up at {level} per world:",
        per_world,
    ])  # fmt: skip


def speedup_json(rows: Sequence[SpeedupRow], config: ReportConfig) -> dict:
    """The speed-up numbers as JSON-serialisable data (bounds as intervals)."""
    return {
        "reference": config.speedup_reference,
        "level": config.speedup_level,
        "rows": [
            {
                "method": row.method,
                "robots": row.robots,
                "episodes": row.episodes,
                "median_steps": {f"{x:g}": v.json() for x, v in row.median_steps.items()},
                "reference_median_steps": {
                    f"{x:g}": v.json() for x, v in row.reference_steps.items()
                },
                "speedup": row.speedup.json(),
                "episode_median_speedup": row.episode_speedup.json(),
                "speedup_by_world": {w: v.json() for w, v in row.by_world.items()},
                "path_length_m": _finite(row.path_length_m),
                "idle_steps_per_robot": _finite(row.idle_steps),
                "overlap": _finite(row.overlap),
            }
            for row in rows
        ],
    }


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def plot_speedup(path: Path, rows: Sequence[SpeedupRow], config: ReportConfig) -> None:
    """speedup.png: pooled speed-up against N per team method (solid) and its median per
    episode (dotted), with the k-fold line."""
    size = config.curve_panel_inches
    fig, ax = plt.subplots(figsize=(size * 1.25, size))
    most = max(row.robots for row in rows)
    ns = np.arange(1, most + 1)
    ax.plot(ns, ns, "k--", linewidth=1, label="k-fold (y = N)")
    reference = (config.speedup_reference, 1)
    teams = [row for row in rows if (row.method, row.robots) != reference]
    for method in order_methods({row.method for row in teams}, ()):
        mine = sorted((row for row in teams if row.method == method), key=lambda r: r.robots)
        colour = None
        lines = (("speedup", "-", method), ("episode_speedup", ":", f"{method}, per episode"))
        for kind, style, label in lines:
            points = [(row.robots, getattr(row, kind)) for row in mine]
            if mine[0].robots != 1:  # N = 1 is the reference robot itself
                points.insert(0, (1, Interval(1.0, 1.0)))
            line = ax.plot(*_line(points), marker="o", linestyle=style, color=colour, label=label)
            colour = line[0].get_color()
            for n, value in points:
                if value.known and not value.exact:
                    _draw_bound(ax, n, value, colour)
    ax.set_xlabel("robots N")
    ax.set_ylabel(f"speed-up to {config.speedup_level * 100:g} % coverage")
    ax.set_xticks(ns)
    ax.set_xlim(0.8, most + 0.2)
    ax.set_ylim(0, most + 0.5)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=config.dpi, format="png")
    plt.close(fig)


def _line(points: list[tuple[int, Interval]]) -> tuple[list[int], list[float]]:
    """The exactly known points of a method's line (bounds are drawn apart)."""
    exact = [(n, v.low) for n, v in points if v.known and v.exact]
    return [n for n, _ in exact], [v for _, v in exact]


def _draw_bound(ax: plt.Axes, n: int, value: Interval, colour: str) -> None:
    """A triangle at the bound pointing the way the value lies (both ends for an interval)."""
    if value.low > 0:
        ax.plot(n, value.low, marker="^", color=colour, linestyle="none")
    if math.isfinite(value.high):
        ax.plot(n, value.high, marker="v", color=colour, linestyle="none")
