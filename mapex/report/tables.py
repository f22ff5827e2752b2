"""The report's numbers and their Markdown / JSON form.

Per method the mean +- standard error over runs of the coverage, IoU and TU AUCs
(docs/algorithms.md#metrics), pooled and per world; MapEx's relative improvement over every
other method in the paper's form (AUC_ref - AUC_other) / AUC_other x 100 %
(docs/algorithms.md#protocol); the number of runs per world and method; a note when runs have
different time budgets (their AUCs are then not comparable)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from mapex.episode import IOU_REACHED
from mapex.methods.information_gain import MapEx
from mapex.report.config import ReportConfig
from mapex.report.runs import METRIC_LABELS, METRICS, RunRecord

REFERENCE_METHOD = MapEx.name


@dataclass(frozen=True)
class Stat:
    """Mean and standard error (sample sd / sqrt n; NaN below two runs) of n finite values."""

    mean: float
    se: float
    n: int


@dataclass(frozen=True)
class MethodRow:
    method: str
    runs: int
    early_terminations: int
    explored_ends: int  # early ends with no frontier left
    unreachable_ends: int  # early ends with frontiers left, none reachable
    iou_ends: int  # ends by `--until-iou` (G's IoU reached the level)
    degraded_runs: int
    auc: dict[str, Stat]


@dataclass(frozen=True)
class Table:
    """AUC rows in method order, pooled over all worlds and per world."""

    rows: tuple[MethodRow, ...]
    by_world: dict[str, tuple[MethodRow, ...]]

    @property
    def methods(self) -> tuple[str, ...]:
        return tuple(row.method for row in self.rows)

    def row(self, method: str) -> MethodRow | None:
        return next((row for row in self.rows if row.method == method), None)


def mean_se(values: Sequence[float]) -> Stat:
    """Mean and standard error of the finite `values`."""
    finite = np.asarray([v for v in values if math.isfinite(v)], dtype=np.float64)
    n = int(finite.size)
    mean = float(finite.mean()) if n else math.nan
    se = float(finite.std(ddof=1) / math.sqrt(n)) if n >= 2 else math.nan
    return Stat(mean, se, n)


def order_methods(methods: Iterable[str], order: Sequence[str]) -> list[str]:
    """`methods` in `order`, then any others alphabetically."""
    present = set(methods)
    return [m for m in order if m in present] + sorted(present - set(order))


def method_rows(runs: Sequence[RunRecord], order: Sequence[str]) -> tuple[MethodRow, ...]:
    """One AUC row per method of `runs`."""
    rows = []
    for method in order_methods((r.method for r in runs), order):
        mine = [r for r in runs if r.method == method]
        rows.append(
            MethodRow(
                method=method,
                runs=len(mine),
                early_terminations=sum(r.early_termination for r in mine),
                explored_ends=sum(r.end_reason == "explored" for r in mine),
                unreachable_ends=sum(r.end_reason == "unreachable" for r in mine),
                iou_ends=sum(r.end_reason == IOU_REACHED for r in mine),
                degraded_runs=sum(r.degraded for r in mine),
                auc={m: mean_se([r.auc(m) for r in mine]) for m in METRICS},
            )
        )
    return tuple(rows)


def auc_table(runs: Sequence[RunRecord], order: Sequence[str] | None = None) -> Table:
    """Per method the mean +- SE over runs of each AUC, pooled and per world (sorted)."""
    order = ReportConfig().method_order if order is None else order
    worlds = sorted({r.world for r in runs})
    by_world = {w: method_rows([r for r in runs if r.world == w], order) for w in worlds}
    return Table(method_rows(runs, order), by_world)


def relative_improvement(reference: float, other: float) -> float:
    """(reference - other) / other x 100 %: docs/algorithms.md#protocol: "reference beats other
    by k %"."""
    if not (math.isfinite(reference) and math.isfinite(other)) or other == 0:
        return math.nan
    return (reference - other) / other * 100.0


def relative_improvements(
    table: Table, reference: str = REFERENCE_METHOD
) -> dict[str, dict[str, float]]:
    """For every method but `reference`: the reference's improvement per metric in % and
    their `mean` (the paper's "across all metrics"); empty without a reference row."""
    ref = table.row(reference)
    if ref is None:
        return {}
    result = {}
    for row in table.rows:
        if row.method == reference:
            continue
        per_metric = {m: relative_improvement(ref.auc[m].mean, row.auc[m].mean) for m in METRICS}
        finite = [v for v in per_metric.values() if math.isfinite(v)]
        per_metric["mean"] = float(np.mean(finite)) if finite else math.nan
        result[row.method] = per_metric
    return result


def run_counts(runs: Sequence[RunRecord], order: Sequence[str]) -> dict[str, dict[str, int]]:
    """world -> method -> number of runs (every method of `runs` in every world, 0 if none)."""
    methods = order_methods((r.method for r in runs), order)
    return {
        w: {m: sum(r.world == w and r.method == m for r in runs) for m in methods}
        for w in sorted({r.world for r in runs})
    }


def budget_warning(runs: Sequence[RunRecord]) -> str | None:
    """A note when the runs have different time budgets (their AUCs are then not comparable)."""
    budgets = sorted({int(r.metrics["steps"]) for r in runs if "steps" in r.metrics})
    if len(budgets) > 1:
        return f"runs have different time budgets T ({', '.join(map(str, budgets))})"
    return None


def missing_note(missing: Sequence[str]) -> str | None:
    """A note naming the runs left out of an incomplete report (`--allow-missing`)."""
    if not missing:
        return None
    return f"reported without {len(missing)} missing or unreadable run(s): {', '.join(missing)}"


# ---------------------------------------------------------------- markdown / json


def _fmt_stat(stat: Stat) -> str:
    if not math.isfinite(stat.mean):
        return "–"
    se = f"{stat.se:.3f}" if math.isfinite(stat.se) else "–"
    return f"{stat.mean:.3f} ± {se}"


def _fmt_early_ends(row: MethodRow) -> str:
    """`3 (2 / 1 / 0)`; runs recorded before end reasons existed count in the total only."""
    reasons = (row.explored_ends, row.unreachable_ends, row.iou_ends)
    return f"{row.early_terminations} ({' / '.join(map(str, reasons))})"


def _fmt_percent(value: float) -> str:
    return f"{value:+.1f} %" if math.isfinite(value) else "–"


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def auc_markdown(rows: Sequence[MethodRow]) -> str:
    """The AUC table: mean ± standard error over runs, and the early ends by reason."""
    header = ["method", "runs", "early end (explored / unreachable / IoU)", "degraded runs"]
    header += [f"{METRIC_LABELS[m]} AUC" for m in METRICS]
    body = [
        [r.method, r.runs, _fmt_early_ends(r), r.degraded_runs]
        + [_fmt_stat(r.auc[m]) for m in METRICS]
        for r in rows
    ]
    return markdown_table(header, body)


def improvements_markdown(improvements: dict[str, dict[str, float]], reference: str) -> str:
    """The relative-improvement table of the reference method over each other method."""
    header = [f"{reference} over", *(METRIC_LABELS[m] for m in METRICS), "mean"]
    body = [
        [method, *(_fmt_percent(v[m]) for m in (*METRICS, "mean"))]
        for method, v in improvements.items()
    ]
    return markdown_table(header, body)


def counts_markdown(counts: dict[str, dict[str, int]]) -> str:
    """Runs per world (rows) and method (columns)."""
    methods = list(next(iter(counts.values()), {}))
    body = [[w, *(c[m] for m in methods), sum(c.values())] for w, c in counts.items()]
    return markdown_table(["world", *methods, "total"], body)


def render_markdown(
    table: Table,
    improvements: dict[str, dict[str, float]],
    counts: dict[str, dict[str, int]],
    reference: str,
    notes: Sequence[str] = (),
    sections: Sequence[str] = (),
    world_sections: dict[str, str] | None = None,
) -> str:
    """The whole report.md; `sections` (Markdown) follow the improvements,
    `world_sections[world]` that world's AUC table."""
    n_runs = sum(r.runs for r in table.rows)
    parts = [
        "# Exploration results",
        f"{n_runs} runs, {len(counts)} worlds. AUC = mean of a run's curve over its samples "
        "(coverage and IoU every 50 steps, TU every 100); mean ± standard error over runs.",
        *(f"**Note:** {note}." for note in notes),
        "## AUC (all worlds)",
        auc_markdown(table.rows),
        f"## Relative improvement of {reference}",
        "(AUC_" + reference + " − AUC_other) / AUC_other × 100 %.",
        improvements_markdown(improvements, reference)
        if improvements
        else f"No {reference} runs: no improvements to report.",
        *sections,
        "## Runs per world",
        counts_markdown(counts),
        "## AUC per world",
    ]
    for world, rows in table.by_world.items():
        parts += [f"### {world}", auc_markdown(rows)]
        if world_sections and world in world_sections:
            parts.append(world_sections[world])
    return "\n\n".join(parts) + "\n"


def _json_number(value: float) -> float | None:
    return round(value, 6) if math.isfinite(value) else None


def _rows_json(rows: Sequence[MethodRow]) -> dict:
    return {
        r.method: {
            "runs": r.runs,
            "early_terminations": r.early_terminations,
            "early_ends_by_reason": {
                "explored": r.explored_ends,
                "unreachable": r.unreachable_ends,
                "iou_reached": r.iou_ends,
            },
            "degraded_runs": r.degraded_runs,
            "auc": {
                m: {"mean": _json_number(s.mean), "se": _json_number(s.se), "n": s.n}
                for m, s in r.auc.items()
            },
        }
        for r in rows
    }


def report_json(
    table: Table,
    improvements: dict[str, dict[str, float]],
    counts: dict[str, dict[str, int]],
    reference: str,
    notes: Sequence[str] = (),
) -> dict:
    """The numbers of report.md as JSON-serialisable data (NaN -> null)."""
    return {
        "methods": _rows_json(table.rows),
        "by_world": {w: _rows_json(rows) for w, rows in table.by_world.items()},
        "improvements": {
            "reference": reference,
            "over": {
                m: {k: _json_number(v) for k, v in values.items()}
                for m, values in improvements.items()
            },
        },
        "run_counts": counts,
        "notes": list(notes),
    }
