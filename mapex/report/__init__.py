"""`python -m mapex.report RESULTS_DIR [RESULTS_DIR ...]`: the evaluation report of finished runs.

Reads the run folders written by mapex.results (hidden `.name` folders are runs still
being written and are ignored), of one folder or merged from several (the shards of one
`services.evaluate --shard K/N` experiment: docs/deploy.md), and writes, in `--out`
(default RESULTS_DIR/report; required with several folders),
report.md / report.json (the AUC tables, MapEx's relative improvement, time to level,
teams) and the figures; what each holds is in docs/algorithms.md#the-report.

Modules: runs (loading run folders), tables (numbers, Markdown and JSON), figures (curves
and snapshots), reach (time to level), teams (the team part), speedup (teams against one
robot in time); this one assembles the report and holds the command line.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mapex.exit_codes import EXIT_USAGE
from mapex.report.config import ReportConfig
from mapex.report.figures import (
    MeanCurve,
    choose_snapshot_runs,
    mean_curve,
    plot_curves,
    plot_snapshots,
    snapshot_columns,
    world_file_name,
)
from mapex.report.reach import (
    REACH_FIGURE,
    PairRow,
    paired_markdown,
    paired_rows,
    plot_reach,
    reach_json,
    reach_markdown,
    reach_table,
)
from mapex.report.runs import (
    METRIC_LABELS,
    METRICS,
    ReportError,
    RunRecord,
    Snapshots,
    Warn,
    campaign_episodes,
    load_folders,
    load_run,
    load_runs,
    load_snapshots,
    load_snapshots_or_warn,
    missing_runs,
    warn_stderr,
)
from mapex.report.speedup import (
    SPEEDUP_FIGURE,
    plot_speedup,
    speedup_json,
    speedup_markdown,
    team_speedup_rows,
)
from mapex.report.tables import (
    REFERENCE_METHOD,
    MethodRow,
    Stat,
    Table,
    auc_markdown,
    auc_table,
    budget_warning,
    counts_markdown,
    improvements_markdown,
    mean_se,
    method_rows,
    missing_note,
    order_methods,
    relative_improvement,
    relative_improvements,
    render_markdown,
    report_json,
    run_counts,
)
from mapex.report.teams import (
    TEAMS_FIGURE,
    load_trajectories,
    plot_teams,
    team_markdown,
    team_runs,
    team_summary,
)
from mapex.results import staged_file

__all__ = [
    "CURVES_FIGURE",
    "JSON_FILE",
    "MARKDOWN_FILE",
    "METRICS",
    "METRIC_LABELS",
    "REFERENCE_METHOD",
    "REPORT_DIR_NAME",
    "SNAPSHOTS_FIGURE",
    "MeanCurve",
    "MethodRow",
    "ReportError",
    "ReportFiles",
    "RunRecord",
    "Snapshots",
    "Stat",
    "Table",
    "Warn",
    "auc_markdown",
    "auc_table",
    "budget_warning",
    "build_parser",
    "campaign_episodes",
    "choose_snapshot_runs",
    "counts_markdown",
    "improvements_markdown",
    "load_folders",
    "load_run",
    "load_runs",
    "load_snapshots",
    "main",
    "mean_curve",
    "missing_runs",
    "missing_note",
    "mean_se",
    "method_rows",
    "order_methods",
    "plot_curves",
    "plot_snapshots",
    "relative_improvement",
    "relative_improvements",
    "render_markdown",
    "report_command",
    "report_json",
    "run_counts",
    "snapshot_columns",
    "warn_stderr",
    "world_file_name",
    "write_report",
]

REPORT_DIR_NAME = "report"
MARKDOWN_FILE = "report.md"
JSON_FILE = "report.json"
CURVES_FIGURE = "curves.png"
SNAPSHOTS_FIGURE = "snapshots.png"


@dataclass(frozen=True)
class ReportFiles:
    markdown: Path
    json: Path
    figures: tuple[Path, ...]


def write_report(
    runs: Sequence[RunRecord],
    out_dir: Path,
    config: ReportConfig | None = None,
    snapshot_pick: RunRecord | None = None,
    warn: Warn = warn_stderr,
    missing: Sequence[str] = (),
) -> tuple[ReportFiles, str]:
    """Write report.md, report.json and the figures of `runs` to `out_dir`; return the files
    and the Markdown summary (AUC and improvement tables) for the terminal."""
    if not runs:
        raise ReportError("no runs to report")
    config = ReportConfig() if config is None else config
    order = config.method_order
    table = auc_table(runs, order)
    improvements = relative_improvements(table, REFERENCE_METHOD)
    counts = run_counts(runs, order)
    notes = [n for n in (budget_warning(runs), missing_note(missing)) if n]
    for note in notes:
        warn(note)
    out_dir.mkdir(parents=True, exist_ok=True)
    markdown = out_dir / MARKDOWN_FILE
    teams = team_summary(team_runs(runs), order)
    reach = reach_table(runs, order)
    pairs = paired_rows(runs, config.paired_comparisons, config.paired_level)
    sections = reach_sections(reach, pairs)
    per_world = {
        world: reach_markdown(mine)
        for world in table.by_world
        if (mine := reach_table([r for r in runs if r.world == world], order))
    }
    text = render_markdown(
        table, improvements, counts, REFERENCE_METHOD, notes, sections, per_world
    )
    if teams:
        text += "\n" + team_markdown(teams) + "\n"
    speedups = team_speedup_rows(runs, config)
    if speedups:
        text += "\n" + speedup_markdown(speedups, config) + "\n"
    with staged_file(markdown) as partial:
        partial.write_text(text)
    data = report_json(table, improvements, counts, REFERENCE_METHOD, notes)
    data.update(reach_json(reach, pairs))
    figures = _write_curves(runs, table, out_dir, config)
    if reach:
        figures.append(out_dir / REACH_FIGURE)
        with staged_file(figures[-1]) as partial:
            plot_reach(partial, runs, order, config)
    snapshots = _write_snapshots(runs, out_dir, config, snapshot_pick, warn)
    if snapshots is not None:
        figures.append(out_dir / SNAPSHOTS_FIGURE)
        data.update(snapshots)
    if teams:
        data["teams"] = teams
        data["team_snapshot_runs"] = _write_teams(team_runs(runs), out_dir, config, warn)
        figures.append(out_dir / TEAMS_FIGURE)
    if speedups:
        data["speedup"] = speedup_json(speedups, config)
        figures.append(out_dir / SPEEDUP_FIGURE)
        with staged_file(figures[-1]) as partial:
            plot_speedup(partial, speedups, config)
    path_json = out_dir / JSON_FILE
    with staged_file(path_json) as partial:
        partial.write_text(json.dumps(data, indent=2) + "\n")
    summary = auc_markdown(table.rows)
    if improvements:
        summary += "\n\n" + improvements_markdown(improvements, REFERENCE_METHOD)
    if reach:
        summary += "\n\n" + reach_markdown(reach)
    return ReportFiles(markdown, path_json, tuple(figures)), summary


def reach_sections(reach: dict, pairs: Sequence[PairRow]) -> list[str]:
    """The Markdown sections of the time to a level and of the paired differences."""
    sections = []
    if reach:
        sections += [
            "## Time to a level",
            "Median first step at which the metric reached the level (in brackets: runs that "
            "never did, counted as later than all; the median is `never` when they are half "
            "or more). reach.png: the share of runs there by step t.",
            reach_markdown(reach),
        ]
    if pairs:
        sections += [
            "## Paired differences",
            "Per episode (same world, start and seed) first − second: mean ± standard error "
            "of the AUC differences, and how often the first method reached the level sooner.",
            paired_markdown(pairs),
        ]
    return sections


def _write_curves(
    runs: Sequence[RunRecord], table: Table, out_dir: Path, config: ReportConfig
) -> list[Path]:
    """curves.png over all worlds, then curves-<world>.png per world; returns their paths."""
    order = config.method_order
    figures = [out_dir / CURVES_FIGURE]
    with staged_file(figures[0]) as partial:
        plot_curves(partial, runs, f"all worlds ({len(runs)} runs)", order, config)
    for world in table.by_world:
        mine = [r for r in runs if r.world == world]
        figures.append(out_dir / world_file_name(world))
        with staged_file(figures[-1]) as partial:
            plot_curves(partial, mine, f"{world} ({len(mine)} runs)", order, config)
    return figures


def _write_snapshots(
    runs: Sequence[RunRecord],
    out_dir: Path,
    config: ReportConfig,
    pick: RunRecord | None,
    warn: Warn,
) -> dict | None:
    """snapshots.png; returns its report.json entries, or None (with a warning) when no run
    has snapshots."""
    chosen = choose_snapshot_runs(runs, config.method_order, pick, warn)
    if not chosen:
        warn("no run has snapshots.npz: snapshots.png not written")
        return None
    pairs = [(r, load_snapshots_or_warn(r, warn)) for r in chosen]
    with staged_file(out_dir / SNAPSHOTS_FIGURE) as partial:
        steps = plot_snapshots(partial, pairs, config)
    return {"snapshot_steps": list(steps), "snapshot_runs": [r.name for r in chosen]}


def _write_teams(
    runs: Sequence[RunRecord], out_dir: Path, config: ReportConfig, warn: Warn
) -> list[str]:
    """teams.png of one team run per team method, on one world and start; returns their
    names."""
    chosen = choose_snapshot_runs(runs, config.method_order, None, warn) or [runs[0]]
    panels = []
    for run in chosen:
        snaps = load_snapshots_or_warn(run, warn)
        last = int(snaps.steps[-1]) if snaps is not None and len(snaps.steps) else 0
        panels.append((run, snaps, load_trajectories(run, last)))
    with staged_file(out_dir / TEAMS_FIGURE) as partial:
        plot_teams(partial, panels, config, warn)
    return [r.name for r in chosen]


# ---------------------------------------------------------------- command line


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m mapex.report",
        description="Summarise a folder of finished runs (one sub-folder per run, as written by "
        "`python -m mapex run`): AUC table (mean ± standard error per method), MapEx's relative "
        "improvements, run counts, metric curves and map snapshots. Folders whose name starts "
        "with '.' are runs still being written and are ignored.",
    )
    parser.add_argument(
        "results_dirs",
        type=Path,
        nargs="+",
        metavar="RESULTS_DIR",
        help="folder of runs; several (e.g. the shards of one services.evaluate experiment) "
        "are merged, an episode found twice counted once if its records agree",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help=f"output folder; default: RESULTS_DIR/{REPORT_DIR_NAME} (one RESULTS_DIR)",
    )
    parser.add_argument(
        "--snapshot-run",
        default=None,
        metavar="NAME",
        help="run folder name whose world and start snapshots.png shows for every method; "
        "default: the first world/start that every method has",
    )
    parser.add_argument(
        "--allow-missing",
        action="store_true",
        help="report even when runs are missing or unreadable (an episode that a folder's "
        "campaign.json lists, or a method absent on some world/start/seed that others have); "
        "the report then lists them",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        files, summary = report_command(args)
    except (ReportError, OSError) as error:
        print(f"mapex.report: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    print(summary)
    print(f"\nwrote {files.markdown}, {files.json} and {len(files.figures)} figures")
    return 0


def report_command(args: argparse.Namespace) -> tuple[ReportFiles, str]:
    results_dirs: list[Path] = list(dict.fromkeys(args.results_dirs))  # each folder once
    for results_dir in results_dirs:
        if not results_dir.is_dir():
            raise ReportError(f"results directory {results_dir} does not exist")
    if args.out is None and len(results_dirs) > 1:
        raise ReportError("several RESULTS_DIRs: name the merged report's folder with --out")
    out_dir = results_dirs[0] / REPORT_DIR_NAME if args.out is None else args.out
    reports = [out_dir, *(results_dir / REPORT_DIR_NAME for results_dir in results_dirs)]
    skipped: list[str] = []
    runs = load_folders(results_dirs, exclude=reports, skipped=skipped)
    if not runs:
        raise ReportError(f"no finished runs in {' '.join(map(str, results_dirs))}")
    unreadable = [f"{name} (unreadable)" for name in skipped]
    have = {run.name for run in runs}
    expected = [name for name in campaign_episodes(results_dirs) if name not in have]
    absent = sorted({*missing_runs(runs), *expected} - set(skipped))
    gaps = unreadable + absent
    if gaps and not args.allow_missing:
        raise ReportError(
            f"{len(gaps)} run(s) missing or unreadable (first: {gaps[0]}): complete them (rerun"
            " the evaluation) or pass --allow-missing to report without them"
        )
    pick = None
    if args.snapshot_run is not None:
        pick = next((r for r in runs if r.name == args.snapshot_run), None)
        if pick is None:
            raise ReportError(f"--snapshot-run: no finished run named '{args.snapshot_run}'")
    return write_report(runs, out_dir, snapshot_pick=pick, missing=gaps)
