"""`python -m mapex.audit`: does exploration ever give up while there is room left to explore?

Every method given runs `--steps` steps from `--starts` start cells spread over each map. A
run that ended early while more than `--max-unknown` of the valid cells the robot could
reach were still unknown is flagged, and the command exits 1 when any run is. A
benchmark-style check: it prints figures and does not run as part of the test suite.

    python -m mapex.audit --maps ../shared/data/kth_dev/50015847 generated:0 \\
        [--starts 25] [--methods nearest,observed_map] [--steps 1000] [--jobs 2]

What is measured: docs/benchmarks.md#the-stall-audit-python--m-mapexaudit.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mapex.config import (
    ConfigError,
    ExplorationConfig,
    add_override_argument,
    apply_overrides,
    argparse_type,
    check_process_count,
    parse_seed,
)
from mapex.episode import run_episode
from mapex.exit_codes import EXIT_FAILED, EXIT_USAGE
from mapex.grid import FREE, OCCUPIED, UNKNOWN, Cell
from mapex.methods import METHODS, parse_method_list
from mapex.navigation import cost_map, reachable_mask
from mapex.prediction import add_predictor_argument, make_predictor
from mapex.worlds import World, WorldError, load_world, world_spec_help
from mapex.worlds.starts import eligible_start_cells

DEFAULT_METHODS = ("nearest", "observed_map")


@dataclass(frozen=True)
class AuditRow:
    """One audited run."""

    world: str
    start: Cell
    method: str
    end_reason: str
    end_step: int | None
    final_coverage: float
    unknown_reachable_share: float
    flagged: bool


def spread_starts(world: World, count: int, clearance_cells: int, seed: int) -> list[Cell]:
    """`count` eligible start cells spread over the map: a seeded random first cell, then
    each next the eligible cell farthest from those taken (ties: row-major first)."""
    cells = np.argwhere(eligible_start_cells(world, clearance_cells))
    if len(cells) == 0:
        raise WorldError(f"world '{world.name}': no eligible start cell")
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(len(cells)))]
    nearest = np.full(len(cells), np.inf)
    while len(chosen) < min(count, len(cells)):
        offsets = cells - cells[chosen[-1]]
        nearest = np.minimum(nearest, np.hypot(offsets[:, 0], offsets[:, 1]))
        chosen.append(int(np.argmax(nearest)))
    return [(int(cells[i][0]), int(cells[i][1])) for i in chosen]


def reachable_valid_cells(world: World, start: Cell, config: ExplorationConfig) -> np.ndarray:
    """Bool map: valid free cells the robot could reach from `start` knowing the whole map."""
    known = np.where(world.occupancy, OCCUPIED, FREE).astype(np.uint8)
    cost = cost_map(known, config.navigation)
    return reachable_mask(cost, start) & world.valid_space & ~world.occupancy


def audit_run(
    world_spec: str, start: Cell, method: str, config: ExplorationConfig, predictor: str
) -> AuditRow:
    """Run one episode and judge how it ended."""
    world = load_world(world_spec, config.world.max_cells)
    uses = METHODS[method].uses_prediction
    ensemble = make_predictor(predictor, world.occupancy) if uses else None
    result = run_episode(world, method, ensemble, start, 0, config)
    reachable = reachable_valid_cells(world, start, config)
    unknown = float((result.final_observed[reachable] == UNKNOWN).mean()) if reachable.any() else 0
    return AuditRow(
        world=world.name,
        start=start,
        method=method,
        end_reason=result.end_reason,
        end_step=result.finished_at,
        final_coverage=float(result.curves.coverage[-1]),
        unknown_reachable_share=unknown,
        flagged=False,
    )


def flag(row: AuditRow, max_unknown: float) -> AuditRow:
    """The row, flagged when the run ended early with too much reachable space unknown."""
    stalled = row.end_reason != "budget" and row.unknown_reachable_share > max_unknown
    return replace(row, flagged=stalled)


def rows_markdown(rows: list[AuditRow]) -> str:
    """Every run: map, start, method, end reason and step, coverage, reachable unknown."""
    lines = [
        "| map | start | method | end | at step | final coverage | reachable unknown | flag |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.world} | {r.start[0]},{r.start[1]} | {r.method} | {r.end_reason} | "
            f"{'-' if r.end_step is None else r.end_step} | {r.final_coverage:.3f} | "
            f"{r.unknown_reachable_share:.1%} | {'STALL' if r.flagged else ''} |"
        )
    return "\n".join(lines)


def summary_markdown(rows: list[AuditRow]) -> str:
    """Per map and method: runs, ends by reason, flagged runs, median and worst unknown."""
    lines = [
        "| map | method | runs | budget / explored / unreachable | flagged | "
        "reachable unknown at end: median / worst |",
        "|---|---|---|---|---|---|",
    ]
    groups = sorted({(r.world, r.method) for r in rows})
    for world, method in groups:
        mine = [r for r in rows if (r.world, r.method) == (world, method)]
        ends = " / ".join(
            str(sum(r.end_reason == why for r in mine))
            for why in ("budget", "explored", "unreachable")
        )
        shares = [r.unknown_reachable_share for r in mine]
        lines.append(
            f"| {world} | {method} | {len(mine)} | {ends} | {sum(r.flagged for r in mine)} | "
            f"{statistics.median(shares):.1%} / {max(shares):.1%} |"
        )
    return "\n".join(lines)


def _audit_job(job: tuple) -> AuditRow:
    return audit_run(*job)


def run_audit(jobs: list[tuple], workers: int, show_progress: bool) -> list[AuditRow]:
    """Every job (world spec, start, method, config, predictor), `workers` processes at once,
    results in job order."""
    bar = tqdm(total=len(jobs), unit="run", disable=not show_progress, file=sys.stderr)
    with bar:
        if workers == 1:
            return [_tick(bar, audit_run(*job)) for job in jobs]
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            return [_tick(bar, row) for row in pool.map(_audit_job, jobs)]


def _tick(bar: tqdm, row: AuditRow) -> AuditRow:
    bar.update(1)
    return row


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m mapex.audit",
        description=__doc__.split("\n\n")[1].replace("\n", " "),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--maps", nargs="+", required=True, metavar="MAP",
                        help=f"the worlds, each {world_spec_help()}")  # fmt: skip
    parser.add_argument("--starts", type=int, default=25, help="start cells per map")
    parser.add_argument("--methods", type=argparse_type(parse_method_list),
                        default=list(DEFAULT_METHODS), help="comma-separated")  # fmt: skip
    parser.add_argument("--steps", type=int, default=1000, help="time budget T")
    parser.add_argument("--seed", type=argparse_type(parse_seed), default=0,
                        help="seed of the start cells")  # fmt: skip
    parser.add_argument("--max-unknown", type=float, default=0.02,
                        help="flag early ends with more reachable cells unknown")  # fmt: skip
    add_predictor_argument(parser)
    parser.add_argument("--jobs", type=int, default=2, help="runs at once (processes)")
    parser.add_argument("--out", type=Path, default=None, help="also write every row as JSON")
    add_override_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def plan_jobs(args: argparse.Namespace, config: ExplorationConfig) -> list[tuple]:
    """(world spec, start, method, config, predictor) for every map, start and method."""
    jobs = []
    for spec in args.maps:
        world = load_world(spec, config.world.max_cells)
        starts = spread_starts(world, args.starts, config.world.start_clearance_cells, args.seed)
        jobs += [(spec, s, m, config, args.predictor) for s in starts for m in args.methods]
    return jobs


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for flag_name in ("starts", "steps", "jobs"):
        if getattr(args, flag_name) < 1:
            parser.error(f"--{flag_name.replace('_', '-')} must be at least 1")
    if not 0 <= args.max_unknown <= 1:
        parser.error("--max-unknown is a share between 0 and 1")
    if args.out is not None and not args.out.parent.is_dir():
        parser.error(f"--out {args.out}: no folder {args.out.parent}")
    try:
        config = apply_overrides(ExplorationConfig(steps=args.steps), args.overrides)
        check_process_count(args.jobs, f"--jobs {args.jobs}")
        config.world.check_starts(args.starts, "--starts")  # each spread over the whole map
        jobs = plan_jobs(args, config)
        rows = run_audit(jobs, args.jobs, not args.no_progress)
        rows = [flag(row, args.max_unknown) for row in rows]
        if args.out is not None:
            args.out.write_text(json.dumps([asdict(r) for r in rows], indent=1) + "\n")
    except (WorldError, ConfigError, OSError) as error:
        print(f"mapex.audit: error: {' '.join(str(error).split())}", file=sys.stderr)
        return EXIT_USAGE
    print(rows_markdown(rows), summary_markdown(rows), sep="\n\n")
    flagged = sum(r.flagged for r in rows)
    print(f"\n{len(rows)} runs, {flagged} flagged (ended early with more than "
          f"{args.max_unknown:.0%} of the reachable cells unknown)")  # fmt: skip
    return EXIT_FAILED if flagged else 0


if __name__ == "__main__":
    sys.exit(main())
