"""Time to a level (docs/algorithms.md#time-to-level): per method the median step at which
coverage and G's IoU first reached each level and how many runs never did, the share of runs
there by step t (reach.png), and paired differences between methods on the same episodes.

A run that never reached a level (within its budget, or before it ran out of frontiers)
counts as later than every run that did: the median is "never" when such runs are half or
more. The share by step t is exact with this censoring, since every run is followed to its end.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mapex.report.config import ReportConfig  # noqa: E402
from mapex.report.runs import METRIC_LABELS, METRICS, RunRecord  # noqa: E402
from mapex.report.tables import Stat, markdown_table, mean_se, order_methods  # noqa: E402

REACH_FIGURE = "reach.png"
Level = tuple[str, float]  # (metric, level), e.g. ("iou", 0.9)


@dataclass(frozen=True)
class ReachStat:
    """Median first step over a method's runs (inf: never, for half or more), how many runs
    reached the level and how many never did."""

    median: float
    reached: int
    never: int


@dataclass(frozen=True)
class PairRow:
    """Method `first` against `second` on the episodes both ran (same world, start, seed):
    mean ± SE of the per-episode AUC difference, and at `level` how often `first` got there
    sooner, later or at the same step (never = later than any step; both never: a tie)."""

    first: str
    second: str
    episodes: int
    auc_difference: dict[str, Stat]
    level: Level
    sooner: int
    later: int
    ties: int


def levels_of(runs: Sequence[RunRecord]) -> list[Level]:
    """Every (metric, level) the runs recorded, coverage first, levels ascending."""
    found = {(metric, level) for run in runs for metric, level in run.reach_levels()}
    return sorted(found, key=lambda item: (item[0] != "coverage", item[1]))


def censored_median(steps: Sequence[int | None]) -> float:
    """Median of first steps, None (never) counted as later than all (NaN for no runs)."""
    if not steps:
        return math.nan
    values = np.array([math.inf if s is None else float(s) for s in steps])
    values.sort()
    middle = len(values) // 2
    if len(values) % 2:
        return float(values[middle])
    low, high = values[middle - 1], values[middle]
    return math.inf if math.isinf(high) else float((low + high) / 2)


def reach_table(
    runs: Sequence[RunRecord], order: Sequence[str]
) -> dict[str, dict[Level, ReachStat]]:
    """method -> (metric, level) -> its median first step and counts (runs with a record)."""
    levels = levels_of(runs)
    table = {}
    for method in order_methods((r.method for r in runs if r.reach_levels()), order):
        mine = [r for r in runs if r.method == method]
        table[method] = {}
        for metric, level in levels:
            steps = [r.reached(metric, level) for r in mine if (metric, level) in r.reach_levels()]
            never = sum(step is None for step in steps)
            table[method][(metric, level)] = ReachStat(
                censored_median(steps), len(steps) - never, never
            )
    return table


def share_reached(runs: Sequence[RunRecord], level: Level, horizon: int) -> np.ndarray:
    """float (horizon + 1,): the share of `runs` that had reached `level` by each step
    (among the runs that recorded it)."""
    runs = [run for run in runs if level in run.reach_levels()]
    counts = np.zeros(horizon + 2)
    for run in runs:
        step = run.reached(*level)
        if step is not None and step <= horizon:
            counts[step] += 1
    return np.cumsum(counts[:-1]) / max(len(runs), 1)


def paired_rows(
    runs: Sequence[RunRecord], pairs: Sequence[tuple[str, str]], level: Level
) -> list[PairRow]:
    """A `PairRow` for each pair of methods that share at least one episode."""
    by_key = {(r.method, r.world, r.start, r.seed): r for r in runs}
    rows = []
    for first, second in pairs:
        matched = [
            (run, by_key[(second, *key[1:])])
            for key, run in by_key.items()
            if key[0] == first and (second, *key[1:]) in by_key
        ]
        if not matched:
            continue
        diffs = {m: mean_se([a.auc(m) - b.auc(m) for a, b in matched]) for m in METRICS}
        both = [
            (a, b) for a, b in matched if level in a.reach_levels() and level in b.reach_levels()
        ]
        ahead = [_order(a.reached(*level), b.reached(*level)) for a, b in both]
        rows.append(
            PairRow(
                first,
                second,
                len(matched),
                diffs,
                level,
                ahead.count(-1),
                ahead.count(1),
                ahead.count(0),
            )  # fmt: skip
        )
    return rows


def _order(a: int | None, b: int | None) -> int:
    """-1 when step a comes before b, 1 after, 0 same (None: never)."""
    a_value = math.inf if a is None else a
    b_value = math.inf if b is None else b
    return (a_value > b_value) - (a_value < b_value)


# ---------------------------------------------------------------- markdown / json / figure


def level_label(level: Level) -> str:
    metric, value = level
    return f"{METRIC_LABELS[metric]} {value * 100:g} %"


def _fmt_reach(stat: ReachStat) -> str:
    median = "never" if math.isinf(stat.median) else f"{stat.median:g}"
    return f"{median} ({stat.never})"


def reach_markdown(table: dict[str, dict[Level, ReachStat]]) -> str:
    """Median first step per method and level, with the runs that never got there."""
    levels = list(next(iter(table.values())))
    header = ["method", "runs", *(level_label(level) for level in levels)]
    body = []
    for method, stats in table.items():
        runs = max(stat.reached + stat.never for stat in stats.values())
        body.append([method, runs, *(_fmt_reach(stats[level]) for level in levels)])
    return markdown_table(header, body)


def paired_markdown(rows: Sequence[PairRow]) -> str:
    """Paired AUC differences and who got to the level first."""
    level = level_label(rows[0].level)
    header = ["first − second", "episodes"]
    header += [f"Δ {METRIC_LABELS[m]} AUC" for m in METRICS]
    header += [f"{level}: sooner / later / same"]
    body = []
    for row in rows:
        cells = [f"{row.first} − {row.second}", row.episodes]
        for metric in METRICS:
            stat = row.auc_difference[metric]
            se = f"{stat.se:.3f}" if math.isfinite(stat.se) else "–"
            cells.append(f"{stat.mean:+.3f} ± {se}" if math.isfinite(stat.mean) else "–")
        cells.append(f"{row.sooner} / {row.later} / {row.ties}")
        body.append(cells)
    return markdown_table(header, body)


def reach_json(table: dict[str, dict[Level, ReachStat]], pairs: Sequence[PairRow]) -> dict:
    """The time-to-level numbers as JSON-serialisable data ("never" as null)."""
    return {
        "time_to_level": {
            method: {
                f"{metric}:{level:g}": {
                    "median_step": None if math.isinf(s.median) else s.median,
                    "reached": s.reached,
                    "never": s.never,
                }
                for (metric, level), s in stats.items()
            }
            for method, stats in table.items()
        },
        "paired": [
            {
                "first": row.first,
                "second": row.second,
                "episodes": row.episodes,
                "auc_difference": {
                    m: {"mean": s.mean if math.isfinite(s.mean) else None, "se": s.se}
                    for m, s in row.auc_difference.items()
                },
                "level": f"{row.level[0]}:{row.level[1]:g}",
                "sooner": row.sooner,
                "later": row.later,
                "same": row.ties,
            }
            for row in pairs
        ],
    }


def plot_reach(
    path: Path, runs: Sequence[RunRecord], order: Sequence[str], config: ReportConfig
) -> None:
    """reach.png: one panel per level, the share of each method's runs there by step t."""
    levels = levels_of(runs)
    horizon = max(int(r.metrics.get("steps", 0)) for r in runs)
    size = config.curve_panel_inches
    fig, axes = plt.subplots(1, len(levels), figsize=(size * len(levels), size), squeeze=False)
    methods = order_methods((r.method for r in runs if r.reach_levels()), order)
    for ax, level in zip(axes[0], levels, strict=True):
        for method in methods:
            mine = [r for r in runs if r.method == method and r.reach_levels()]
            ax.step(np.arange(horizon + 1), share_reached(mine, level, horizon), where="post",
                    label=method)  # fmt: skip
        ax.set_title(f"{level_label(level)} reached")
        ax.set_xlabel("step t")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("share of runs")
    axes[0][-1].legend(fontsize="small", loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=config.dpi, format="png")
    plt.close(fig)
