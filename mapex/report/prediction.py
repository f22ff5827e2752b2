"""`python -m mapex.report.prediction`: what a prediction buys each method that reads one.

For every method that reads the prediction (`mapex`, `pipe`, `mapex_plus`) and every
predictor it ran with (e.g. `lama-v2`, `lama`, `oracle`), its coverage / IoU / TU AUC beside
its no-prediction twin (`mapex.methods.PREDICTION_TWINS`) and the paired differences over
the episodes both ran (same world, start, seed; mean ± standard error). The twin's IoU and
TU are G's map of what the twin saw, so a method is paired with its twin run under the same
predictor; the oracle's G is the truth, so only its coverage is compared (with the twin run
under any predictor: a twin explores the same under all), as for a predictor whose twin did
not run under it. A second table pairs each
predictor with a reference predictor (`--reference`, default `lama-v2`) method by method.
Prints markdown; `--json` also writes the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from mapex.methods import PREDICTION_TWINS
from mapex.prediction import DEFAULT_PREDICTOR
from mapex.prediction.oracle import ORACLE
from mapex.report.runs import METRICS, ReportError, RunRecord, load_folders
from mapex.report.tables import Stat, markdown_table, mean_se
from mapex.results import DEFAULT_PREDICTOR_RECORDS

Episode = tuple[str, str, int]  # world, start, seed


@dataclass(frozen=True)
class PairedRow:
    """One method under one predictor against another run set of the same episodes."""

    method: str
    predictor: str
    against: str  # what it is paired with ("observed_map@lama-v2", "mapex@lama-v2")
    episodes: int
    auc: dict[str, Stat]  # the method's own AUCs over its runs
    difference: dict[str, Stat]  # paired (method - against) per metric; NaN where not compared
    relative: float  # paired coverage difference / the other's mean coverage AUC


def predictor_of(run: RunRecord) -> str:
    """The predictor a run used, the default's old record names read as the default."""
    name = run.metrics.get("predictor")
    return DEFAULT_PREDICTOR if name is None or name in DEFAULT_PREDICTOR_RECORDS else str(name)


def index_runs(runs: Sequence[RunRecord]) -> dict[tuple[str, str], dict[Episode, RunRecord]]:
    """{(method, predictor): {episode: run}} over single-robot runs."""
    index: dict[tuple[str, str], dict[Episode, RunRecord]] = {}
    for run in runs:
        if run.metrics.get("team"):
            continue
        key = (str(run.metrics["method"]), predictor_of(run))
        index.setdefault(key, {})[(run.world, run.start, run.seed)] = run
    return index


def paired_row(
    method: str,
    predictor: str,
    mine: dict[Episode, RunRecord],
    theirs: dict[Episode, RunRecord],
    against: str,
    metrics: Sequence[str] = METRICS,
) -> PairedRow:
    """`mine` against `theirs` over their common episodes, on `metrics` (the others NaN)."""
    common = sorted(set(mine) & set(theirs))
    auc = {m: mean_se([run.auc(m) for run in mine.values()]) for m in METRICS}
    difference = {
        m: mean_se([mine[e].auc(m) - theirs[e].auc(m) for e in common])
        if m in metrics
        else Stat(math.nan, math.nan, 0)
        for m in METRICS
    }
    base = mean_se([theirs[e].auc("coverage") for e in common]).mean
    relative = difference["coverage"].mean / base if base else math.nan
    return PairedRow(method, predictor, against, len(common), auc, difference, relative)


def twin_rows(runs: Sequence[RunRecord]) -> list[PairedRow]:
    """Every (method that reads the prediction, predictor) against its twin."""
    index = index_runs(runs)
    rows = []
    for method, twin in PREDICTION_TWINS.items():
        for predictor in sorted_predictors({p for m, p in index if m == method}):
            mine = index[(method, predictor)]
            if predictor != ORACLE and (twin, predictor) in index:
                label = f"{twin}@{predictor}"
                rows.append(paired_row(method, predictor, mine, index[(twin, predictor)], label))
            elif theirs := _any_predictor(index, twin):  # coverage only: the same under all
                rows.append(paired_row(method, predictor, mine, theirs, twin, ("coverage",)))
    return rows


def reference_rows(runs: Sequence[RunRecord], reference: str) -> list[PairedRow]:
    """Every (method, predictor other than `reference`) against the same method under
    `reference`, for the methods that read the prediction and their twins."""
    index = index_runs(runs)
    rows = []
    for method in [*PREDICTION_TWINS, *PREDICTION_TWINS.values()]:
        if (method, reference) not in index:
            continue
        for predictor in sorted_predictors({p for m, p in index if m == method}):
            if predictor == reference:
                continue
            metrics = ("coverage",) if predictor == ORACLE else METRICS
            theirs, label = index[(method, reference)], f"{method}@{reference}"
            rows.append(
                paired_row(method, predictor, index[(method, predictor)], theirs, label, metrics)
            )
    return rows


def sorted_predictors(names: set[str]) -> list[str]:
    """Learned predictors first (alphabetically), the oracle last."""
    return sorted(names, key=lambda name: (name == ORACLE, name))


def _any_predictor(index: dict, method: str) -> dict[Episode, RunRecord]:
    """The runs of `method` under every predictor, one per episode (its coverage is the
    same under all: a twin reads no prediction)."""
    merged: dict[Episode, RunRecord] = {}
    for (name, _), runs in sorted(index.items()):
        if name == method:
            for episode, run in runs.items():
                merged.setdefault(episode, run)
    return merged


def _stat(stat: Stat, digits: int = 3) -> str:
    if math.isnan(stat.mean):
        return "-"
    se = "" if math.isnan(stat.se) else f" ± {stat.se:.{digits}f}"
    return f"{stat.mean:.{digits}f}{se}"


def _difference(stat: Stat) -> str:
    if math.isnan(stat.mean):
        return "-"
    se = "" if math.isnan(stat.se) else f" ± {stat.se:.3f}"
    return f"{stat.mean:+.3f}{se}"


def rows_markdown(rows: Sequence[PairedRow], against_header: str) -> str:
    """One line per row: the method's AUCs, then its paired differences."""
    header = ["method", "predictor", "runs", "coverage AUC", "IoU AUC", "TU AUC",
              against_header, "Δ coverage", "Δ IoU", "Δ TU", "Δ coverage %"]  # fmt: skip
    body = [
        [
            f"`{row.method}`",
            f"`{row.predictor}`",
            row.episodes,
            *(_stat(row.auc[m]) for m in METRICS),
            f"`{row.against}`",
            *(_difference(row.difference[m]) for m in METRICS),
            "-" if math.isnan(row.relative) else f"{100 * row.relative:+.1f} %",
        ]
        for row in rows
    ]
    return markdown_table(header, body)


def report_markdown(runs: Sequence[RunRecord], reference: str) -> str:
    twins = twin_rows(runs)
    references = reference_rows(runs, reference)
    if not twins and not references:
        raise ReportError(
            "no method that reads the prediction ran beside its twin "
            f"({', '.join(f'{a} / {b}' for a, b in PREDICTION_TWINS.items())}) in these results"
        )
    worlds = sorted({run.world for run in runs})
    lines = [
        f"{len(worlds)} worlds: {', '.join(worlds)}",
        "",
        "Each method against its no-prediction twin (paired over the episodes both ran; the "
        "oracle's IoU and TU are the truth's, so only its coverage is compared, as where the "
        "twin did not run under that predictor):",
        "",
        rows_markdown(twins, "twin"),
        "",
        f"Each predictor against `{reference}`, method by method:",
        "",
        rows_markdown(references, "against"),
    ]
    return "\n".join(lines)


def _finite(value: object) -> object:
    """`value` with every NaN float (at any depth) as None, for JSON."""
    if isinstance(value, float):
        return None if math.isnan(value) else value
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value


def report_json(runs: Sequence[RunRecord], reference: str) -> dict:
    def encode(row: PairedRow) -> dict:
        return _finite(asdict(row))

    return {
        "worlds": sorted({run.world for run in runs}),
        "twins": [encode(row) for row in twin_rows(runs)],
        "reference": reference,
        "against_reference": [encode(row) for row in reference_rows(runs, reference)],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mapex.report.prediction", description=__doc__)
    parser.add_argument("results", nargs="+", type=Path, metavar="RESULTS_DIR")
    parser.add_argument(
        "--reference", default="lama-v2", help="the predictor the others are paired with"
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    try:
        for folder in args.results:
            if not folder.is_dir():
                raise ReportError(f"{folder} is not a folder of runs")
        runs = load_folders(args.results)
        if not runs:
            raise ReportError("no finished runs in " + ", ".join(map(str, args.results)))
        print(report_markdown(runs, args.reference))
        if args.json is not None:
            args.json.write_text(json.dumps(report_json(runs, args.reference), indent=1))
    except (ReportError, OSError) as error:
        print(f"mapex.report.prediction: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
