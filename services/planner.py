"""The planner (robot brain): one robot's exploration episode against a world process.

It runs the loop of `python -m mapex run` (`mapex.episode.run_episode`) for its robot of
the run's team, with the world process as the step source (`services.world_client`) and
the predictor workers as the ensemble (`services.ensemble_client`); members that do not
answer in time are left out and the record says so (docs/design.md#reliability). After each
step it publishes what it knows on `mapex/@v1/<run>/<robot>/...` (`services.publishing`)
and at the end writes the results folder of `python -m mapex run`. With `--world` it
simulates the world itself (batch evaluation runs so), and under `--predictor oracle` serves
that world's ground truth for the oracle worker as a world process would. A planner whose
sensor or motion settings differ from its world's refuses to start. Bad flags: one line,
exit 2; the world gone or refusing a step: one line, exit 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh
from tqdm import tqdm

from mapex.config import ConfigError, ExplorationConfig, argparse_type, parse_seed
from mapex.episode import EpisodeResult, run_episode
from mapex.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from mapex.methods import METHODS
from mapex.prediction import (
    DEFAULT_PREDICTOR,
    ORACLE,
    ORACLE_NOTICE,
    add_predictor_argument,
    served_predictor_problem,
)
from mapex.results import OutputError, check_destination, describe_end, destination, write_results
from mapex.team.starts import team_start_cells
from mapex.worlds import (
    StartSpec,
    World,
    WorldError,
    load_world,
    start_label,
    world_spec_help,
)
from mapex.worlds.starts import add_start_argument, start_cell, start_spec_of
from services.config import RunConfig, ServicesConfig, add_run_config_argument
from services.ensemble_client import ZenohEnsemble
from services.keys import ID_MAX_CHARS, alive_planner_key, is_valid_id, robot_id, run_key
from services.messages import GroundTruth
from services.publishing import RunPublisher
from services.serving import configure_logging, run_token_from_env, supervisor_gone
from services.world_client import (
    StepRefusedError,
    WorldUnavailableError,
    ZenohWorld,
)
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)

log = logging.getLogger("services.planner")

DEFAULT_RUN_CONFIG = RunConfig()

Progress = Callable[[int], None]


class PlannerError(RuntimeError):
    """The run cannot start or go on (no world, start not found); the message is one line."""


@dataclass(frozen=True)
class LocalWorld:
    """Simulate the world in the planner: the world to load, the start (corner or cell) and
    the robots (a team of several deploys around the start and shares one map)."""

    spec: str
    start: StartSpec
    robots: int = 1


def explore(
    session: zenoh.Session,
    run: str,
    robot: int,
    method: str,
    seed: int = 0,
    run_config: RunConfig = DEFAULT_RUN_CONFIG,
    progress: Progress | None = None,
    local: LocalWorld | None = None,
    start: StartSpec | None = None,
    predictor: str = DEFAULT_PREDICTOR,
) -> tuple[EpisodeResult, World]:
    """Run robot `robot`'s episode of `run` with the predictor processes of `predictor`, and
    the world process (or the `local` world simulated here, every robot decided here).
    `start`, with a world process: the start it must have placed the robot at (default:
    whichever it did)."""
    exploration, services = run_config.exploration, run_config.services
    if local is None:
        source = ZenohWorld(session, run, robot, services, run_token_from_env())
        world, starts = _remote_start(source, run, robot, exploration, start)
        robots, here = len(starts), [robot]
    else:
        source, world = None, load_world(local.spec, exploration.world.max_cells)
        starts, robots, here = local.start, local.robots, list(range(local.robots))
        team_start_cells(world, [starts], robots, exploration)  # WorldError if bad
    oversized = prediction_size_warning(world.shape, services)
    if oversized is not None:
        log.warning("%s", oversized)
    publishers = [
        RunPublisher(session, run, robot_id(k), services, local is not None) for k in here
    ]
    publisher = publishers[0]
    tokens = [session.liveliness().declare_token(alive_planner_key(run, robot_id(k))) for k in here]
    oracle = predictor == ORACLE
    truth = serve_ground_truth(session, run, world) if oracle and local is not None else None
    if oracle:
        log.warning("%s", ORACLE_NOTICE)
    walls = world.occupancy if oracle else None
    try:
        with ZenohEnsemble(session, services, predictor, run, walls) as ensemble:
            members = ", ".join(ensemble.served_members)
            publisher.status(0, "starting", f"waiting for members {members} ({predictor})")
            if not ensemble.wait(timeout_s=services.workers_wait_s):
                log.warning("not every member has a live worker: the run starts degraded")
            publisher.status(0, "running", f"{method} on {world.name}")

            def on_step(t, explorers, recorder) -> None:
                if supervisor_gone():
                    raise PlannerError("the supervisor is gone: run abandoned")
                for each, explorer in zip(publishers, explorers, strict=True):
                    each.step(t, explorer, recorder)
                if progress is not None:
                    progress(t)

            result = run_episode(
                world, method, ensemble, starts, seed, exploration, on_step, source, robots, here
            )
        result = dataclasses.replace(result, degraded_from_start=oversized)
        for each in publishers:
            each.finished(result, _summary_line(result))
    except Exception as error:
        publisher.status(0, "failed", f"{type(error).__name__}: {error}")
        raise
    finally:
        for each in publishers:
            each.close()
        for token in tokens:
            token.undeclare()
        if truth is not None:
            truth.undeclare()
    return result, world


def serve_ground_truth(session: zenoh.Session, run: str, world: World) -> zenoh.Queryable:
    """Answer `mapex/@v1/<run>/ground_truth` with `world`'s, as a world process does: the
    oracle worker reads it there (docs/design.md#the-oracle-worker). Undeclare when done."""
    payload = GroundTruth.from_world(world).encode()
    key = run_key(run, "ground_truth")
    return session.declare_queryable(key, lambda query: query.reply(query.key_expr, payload))


def prediction_size_warning(shape: tuple[int, int], services: ServicesConfig) -> str | None:
    """Why a map of `shape` cells is expected to degrade the run (its whole-map predictions
    would miss `predict_timeout_s`), or None when it is small enough."""
    cells = shape[0] * shape[1]
    if cells <= services.predict_max_cells:
        return None
    return (
        f"the map has {cells:,} cells, above the {services.predict_max_cells:,} that a "
        f"prediction is expected to handle within {services.predict_timeout_s:g} s: "
        "predictions may time out and the run is marked degraded from the start"
    )


def _remote_start(
    source: ZenohWorld,
    run: str,
    robot: int,
    exploration: ExplorationConfig,
    expected: StartSpec | None,
) -> tuple[World, list[StartSpec]]:
    """The world process's world and the cells of every robot of the run; PlannerError (one
    line) when the world simulates other sensor or motion settings than this planner's, or
    did not place robot `robot` at `expected` (its corner or cell)."""
    info, world = source.fetch()
    mine = {
        "n_rays": exploration.sensor.n_rays,
        "range_cells": exploration.sensor.range_cells,
        "cells_per_step": exploration.motion.cells_per_step,
    }
    differ = [
        f"{name} {value} (here {mine[name]})"
        for name, value in info.settings().items()
        if value is not None and value != mine[name]
    ]
    if differ:
        raise PlannerError(
            f"the world of run {run} simulates {', '.join(differ)}: start the planner with the "
            "world's --set"
        )
    if not 0 <= robot < len(info.starts):
        raise PlannerError(f"run {run} has {len(info.starts)} robots, there is no robot {robot}")
    clearance = exploration.world.start_clearance_cells
    cells: list[StartSpec] = [(int(row), int(col)) for row, col in info.starts]
    if expected is not None:
        wanted = start_cell(world, expected, clearance)
        if wanted != cells[robot]:
            raise PlannerError(
                f"the world placed robot {robot_id(robot)} at {cells[robot]}, not at its start "
                f"{wanted}"
            )
    if len(cells) == 1:  # a robot alone is named by its start: the corner it stands on
        return world, [start_spec_of(world, cells[0], clearance) if expected is None else expected]
    return world, cells


def _summary_line(result: EpisodeResult) -> str:
    auc = result.curves.auc()
    degraded = len(result.stats.degraded_steps)
    return (
        f"{result.method} on {result.world} ({start_label(result.start_spec)}): coverage AUC "
        f"{auc['coverage']:.3f}, IoU AUC {auc['iou']:.3f}, TU AUC {auc['tu']:.3f}, "
        f"final coverage {result.curves.coverage[-1]:.3f}, {describe_end(result)}, "
        f"degraded re-plans {degraded}"
    )


def main(
    config: zenoh.Config,
    run: str,
    robot: int = 0,
    method: str = "mapex",
    seed: int = 0,
    out: Path | None = None,
    run_config: RunConfig = DEFAULT_RUN_CONFIG,
    progress: Progress | None = None,
    local: LocalWorld | None = None,
    start: StartSpec | None = None,
    predictor: str = DEFAULT_PREDICTOR,
) -> tuple[EpisodeResult, Path]:
    """Open a session, run the episode, write its results folder; return (result, folder)."""
    check_destination(out)
    session = open_session(config)
    try:
        result, world = explore(
            session, run, robot, method, seed, run_config, progress, local, start, predictor
        )
    finally:
        session.close()
    if supervisor_gone():  # the pool went down with it: the end of the run may be degraded
        raise PlannerError("the supervisor is gone: run abandoned, nothing written")
    out_dir = destination(out, result)
    try:
        write_results(result, world, out_dir)
    except OutputError as error:
        raise PlannerError(str(error)) from None
    return result, out_dir


def build_parser() -> argparse.ArgumentParser:
    """The command-line flags: run, robot, method, steps, seed, output and Zenoh's."""
    parser = argparse.ArgumentParser(
        prog="python -m services.planner", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--run", required=True, help="run id, the <run> chunk of the keys")
    parser.add_argument("--robot", type=int, default=0, help="robot index in the run (default 0)")
    parser.add_argument("--method", default="mapex", choices=list(METHODS))
    add_predictor_argument(parser, served=True)
    parser.add_argument(
        "--robots",
        type=int,
        default=1,
        help="with --world: a team of this many robots sharing one map, all decided here",
    )
    parser.add_argument("--steps", type=int, default=1000, help="time budget T (default 1000)")
    parser.add_argument(
        "--seed",
        type=argparse_type(parse_seed),
        default=0,
        help="random seed (UPEN's RRT); default 0",
    )
    parser.add_argument("--out", type=Path, default=None, help="results folder")
    add_run_config_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument(
        "--world",
        default=None,
        help="simulate this world here instead of asking a world process (needs --start): "
        + world_spec_help(),
    )
    add_start_argument(
        parser, None, "with --world where to start, else where the world placed the robot"
    )
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    """Parse flags and run; 0 on success, 1 when the run failed, 2 on a bad flag."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not is_valid_id(args.run):
        parser.error(f"--run {args.run!r} must match [a-z0-9_-]{{1,{ID_MAX_CHARS}}}")
    if args.steps < 1 or args.robot < 0:
        parser.error("--steps must be at least 1 and --robot non-negative")
    if args.world is not None and args.start is None:
        parser.error("--world needs --start")
    if args.robots > 1 and args.world is None:
        parser.error("--robots needs --world (a team is simulated here)")
    if (problem := served_predictor_problem(args.predictor)) is not None:
        parser.error(problem)
    local = None if args.world is None else LocalWorld(args.world, args.start, args.robots)
    configure_logging(f"planner[{args.run}/{robot_id(args.robot)}]")
    try:
        run_config = RunConfig(ExplorationConfig(steps=args.steps)).with_overrides(args.overrides)
        run_config.exploration.team.check_robots(args.robots)
        config = zenoh_config_from_args(args, run_config.services)
    except (ConfigError, ZenohConfigError) as error:
        print(f"services.planner: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    log.info("%s", run_config.describe())
    bar = tqdm(total=args.steps, unit="step", disable=args.no_progress, file=sys.stderr)
    try:
        result, out_dir = main(
            config, args.run, args.robot, args.method, args.seed, args.out, run_config,
            progress=lambda t: bar.update(t - bar.n), local=local, start=args.start,
            predictor=args.predictor,
        )  # fmt: skip
    except (WorldError, OutputError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    except (WorldUnavailableError, StepRefusedError, PlannerError) as error:
        log.error("%s", error)
        return EXIT_FAILED
    except KeyboardInterrupt:
        log.error("interrupted")
        return EXIT_INTERRUPTED
    finally:
        bar.close()
    print(f"{_summary_line(result)} -> {out_dir}")
    return 0


if __name__ == "__main__":
    threading.current_thread().name = "planner"
    sys.exit(run_cli())
