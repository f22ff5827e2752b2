"""`python -m services.up`: the whole distributed simulator on one machine, supervised.

With no arguments it serves the Zenoh hub on tcp/127.0.0.1:7447, spawns the world (the
embedded default world), one predictor worker per ensemble member and the planner, runs a
1000-step MapEx episode with a progress bar and writes the results folder of `python -m
mapex run`; `--predictor oracle` spawns one oracle worker (member g, the ground truth as
the prediction: an upper bound) instead. It forwards the children's logs, restarts a dead
or stuck worker, ends the run with the child's own line when a world exits or a child fails
to start, and stops everything on Ctrl-C. The run's settings (defaults and `--set`) are
built once and handed to every child. Flags: `--help`; deployment on several machines:
deploy/README.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import secrets
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from mapex.budget import add_budget_arguments, resolve_steps
from mapex.config import MAX_SEED, ConfigError, ExplorationConfig, argparse_type, parse_seed
from mapex.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from mapex.methods import METHODS
from mapex.prediction import DEFAULT_PREDICTOR, ORACLE, ORACLE_NOTICE
from mapex.prediction.config import inference_from_args
from mapex.results import DEFAULT_RESULTS_DIR, check_output_folder
from mapex.team.starts import team_start_cells
from mapex.worlds import (
    DEFAULT_SPEC,
    StartSpec,
    World,
    WorldError,
    load_world,
    world_spec_help,
)
from mapex.worlds.starts import add_start_argument, start_argument
from services.bridges.outside_tools import (
    OutsideTools,
    add_outside_tool_arguments,
    bridge_spec,
    check_outside_tool_arguments,
    tool_process_count,
    viewer_specs,
)
from services.config import RunConfig, add_run_config_argument
from services.health import PoolWatch
from services.keys import ID_MAX_CHARS, is_valid_id, robot_id
from services.messages import PoseMessage
from services.pool import (
    HubWatch,
    RunProgress,
    add_pool_arguments,
    adopt_config_file,
    check_hub_answers,
    hub_session_config,
    resolve_pool_predictor,
    worker_specs,
)
from services.serving import RUN_TOKEN_ENV, configure_logging, exit_on_signals, stop_on_signals
from services.supervisor import ProcessSpec, Supervisor, describe_exit
from services.zenoh_config import (
    HUB_HELP,
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
)

RUN_PREFIX_MAX_CHARS = ID_MAX_CHARS - 8  # room for the '-<k>' run suffix
VIEWERS = "viewers"  # the role of the web view and Foxglove server children: never fatal

log = logging.getLogger("services.up")


@dataclass(frozen=True)
class Run:
    """One episode: a world process and one planner per robot. `token`: the run's secret,
    given to its world and planners only (in their environment, not on a command line);
    the world refuses steps without it."""

    run_id: str
    starts: tuple[StartSpec, ...]
    seed: int
    token: str = ""


def plan_runs(
    args: argparse.Namespace, world: World, exploration: ExplorationConfig | None = None
) -> list[Run]:
    """The runs asked for: run k starts at corner start + k (mod 4), or at the one cell; a
    team of several deploys around that start (`mapex.team.starts`)."""
    prefix = args.run_prefix or f"up{os.getpid()}"
    runs = []
    for k in range(args.runs):
        first = (args.start + k) % 4 if isinstance(args.start, int) else args.start
        cells = team_start_cells(world, [first], args.robots, exploration or ExplorationConfig())
        # a robot alone is named by its start as given (the corner), a team by its cells
        starts: tuple[StartSpec, ...] = (first,) if args.robots == 1 else tuple(cells)
        runs.append(Run(f"{prefix}-{k}", starts, args.seed + k, secrets.token_hex(16)))
    return runs


def child_specs(
    args: argparse.Namespace, runs: list[Run], zenoh_flags: list[str], run_config: RunConfig
) -> dict:
    """Process specs by role: 'workers', 'worlds', 'planners'; each child gets the run's
    settings as the `--set` items that rebuild `run_config`."""
    settings = run_config.as_overrides()
    sets = [flag for item in settings for flag in ("--set", item)]
    workers = worker_specs(
        args.members, args.replicas, args.threads, zenoh_flags, inference_from_args(args),
        id_prefix=f"up{os.getpid()}", settings=settings, predictor=args.predictor,
    )  # fmt: skip
    chosen = [] if args.predictor == DEFAULT_PREDICTOR else ["--predictor", args.predictor]
    worlds, planners = [], []
    for run in runs:
        starts = [start_argument(start) for start in run.starts]
        secret = {RUN_TOKEN_ENV: run.token}
        world_args = (
            "--run", run.run_id, "--world", args.world, "--robots", str(len(run.starts)),
            "--starts", *starts, *sets, *zenoh_flags,
        )  # fmt: skip
        worlds.append(ProcessSpec(f"world-{run.run_id}", "services.world", world_args, env=secret))
        for robot in range(len(run.starts)):
            planner_args = [
                "--run", run.run_id, "--robot", str(robot), "--method", args.method,
                "--steps", str(run_config.exploration.steps), "--seed", str(run.seed),
                "--no-progress", "--start", starts[robot], *chosen, *sets,
            ]  # fmt: skip
            if args.out is not None:
                planner_args += ["--out", str(args.out / f"{run.run_id}-{robot_id(robot)}")]
            planners.append(
                ProcessSpec(
                    f"planner-{run.run_id}-{robot_id(robot)}",
                    "services.planner",
                    (*planner_args, *zenoh_flags),
                    env=secret,
                )
            )
    return {"workers": workers, "worlds": worlds, "planners": planners}


def supervise(
    supervisor: Supervisor,
    specs: dict[str, list[ProcessSpec]],
    progress: RunProgress,
    runs: list[Run],
    total_steps: int,
    stop: threading.Event,
    show_progress: bool,
    watch: PoolWatch | None = None,
    hub: HubWatch | None = None,
) -> int:
    """Poll until every planner exits (or `stop`); return the exit code of the whole run.

    `specs` by role as `child_specs` gives them. A world that exits while planners still run
    ends the whole run at once, with the world's own last line: its robots' poses, sequence
    numbers and scans live only in that process, so a restarted world could not resume the
    run soundly. So does any child that fails to start (exit 2: bad flags, missing weights, no
    hub), with its own error line. `watch` kills stuck workers for `poll` to restart; a
    joined hub that is gone (`hub`) ends the run too.
    """
    pending = {spec.name for spec in specs["planners"]}
    failed: list[str] = []
    with tqdm(total=total_steps, unit="step", disable=not show_progress, file=sys.stderr) as bar:
        while pending and not stop.is_set():
            supervisor.poll()
            if watch is not None:
                watch.check()
            fatal = _failed_start(supervisor, specs) or _gone_world(supervisor, specs["worlds"])
            fatal = fatal or (hub.lost() if hub is not None else None)
            if fatal is not None:
                log.error("%s", fatal)
                return EXIT_FAILED
            for name in sorted(pending):
                code = supervisor.returncode(name)
                if code is not None:
                    pending.discard(name)
                    if code != 0:
                        failed.append(f"{name} exited with {code}")
            done = sum(progress.of(run.run_id) for run in runs)
            bar.update(min(done, total_steps) - bar.n)
            time.sleep(supervisor.services.supervision_poll_s)
    if stop.is_set():
        log.info("interrupted: stopping every process")
        return EXIT_INTERRUPTED
    for line in failed:
        log.error("%s", line)
    return EXIT_FAILED if failed else 0


def main(args: argparse.Namespace) -> int:
    """Spawn, supervise and stop everything; the exit code of the run."""
    # A bad world, start or setting fails here in one line, before any process starts.
    run_config = RunConfig(ExplorationConfig(until_iou=args.until_iou))
    run_config = run_config.with_overrides(args.overrides)
    exploration, services = run_config.exploration, run_config.services
    resolve_pool_predictor(args)
    check_process_caps(args, run_config)
    world = load_world(args.world, exploration.world.max_cells)
    args.steps = resolve_steps(args.steps, world)
    exploration = dataclasses.replace(exploration, steps=args.steps)
    run_config = dataclasses.replace(run_config, exploration=exploration)
    runs = plan_runs(args, world, exploration)
    check_output_folder(args.out or DEFAULT_RESULTS_DIR)
    check_outside_tool_arguments(args)
    connect_file = adopt_config_file(args)  # a --config file's mode and endpoints count
    check_hub_answers(args.connect, services, connect_file)
    own_config, zenoh_flags = hub_session_config(args, services)
    specs = child_specs(args, runs, zenoh_flags, run_config)
    specs["tools"] = bridge_spec(args, zenoh_flags)
    specs[VIEWERS] = viewer_specs(args, zenoh_flags)
    if args.predictor == ORACLE:
        log.warning("%s", ORACLE_NOTICE)
    stop = stop_on_signals()
    session = open_session(own_config)
    progress = RunProgress(session, "pose", PoseMessage)
    supervisor = Supervisor(services=services)
    watch = PoolWatch(session, supervisor, specs["workers"], services)
    tools = None
    try:
        tools = OutsideTools(session, args)
        for role in ("tools", VIEWERS, "workers", "worlds", "planners"):
            for spec in specs[role]:
                supervisor.start(spec)
        total = args.steps * sum(len(run.starts) for run in runs)
        hub = HubWatch(session, args.connect, services)
        return supervise(
            supervisor, specs, progress, runs, total, stop, not args.no_progress, watch, hub
        )
    finally:
        if tools is not None:
            tools.close([run.run_id for run in runs])
        supervisor.stop()
        progress.close()
        session.close()


def check_process_caps(args: argparse.Namespace, run_config: RunConfig) -> None:
    """ConfigError (one line, naming the cap) when `--robots` is above `team.max_robots` or
    the processes asked for (a world and --robots planners per run, the workers, the outside
    tools) are more than this machine holds (`ServicesConfig.check_processes`)."""
    run_config.exploration.team.check_robots(args.robots)
    bridges = tool_process_count(args)
    planners, workers = args.runs * args.robots, len(args.members) * args.replicas
    run_config.services.check_processes(
        planners + args.runs + workers + bridges,
        f"--runs {args.runs} x --robots {args.robots} planners, {args.runs} worlds and "
        f"{len(args.members)} x --replicas {args.replicas} workers"
        + (f" and {bridges} outside tools" if bridges else ""),
    )


def _failed_start(supervisor: Supervisor, specs: dict[str, list[ProcessSpec]]) -> str | None:
    """A line naming the first child that exited with a usage error, with its last line
    (a viewer's exit, logged by the supervisor, never ends the run)."""
    for spec in (spec for role, of in specs.items() if role != VIEWERS for spec in of):
        if supervisor.returncode(spec.name) == EXIT_USAGE:
            said = supervisor.last_words(spec.name)
            return f"{spec.name} failed to start ({said}): stopping the run"
    return None


def _gone_world(supervisor: Supervisor, worlds: list[ProcessSpec]) -> str | None:
    """A line naming the first world process that has exited, with its last output line."""
    for spec in worlds:
        code = supervisor.returncode(spec.name)
        if code is not None:
            said = supervisor.last_words(spec.name)
            return (
                f"{spec.name} exited with {describe_exit(code)} before its run ended "
                f"({said}): stopping the run"
            )
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.up",
        description=__doc__.split("\n\n")[1].replace("\n", " "),
    )
    parser.add_argument("--world", default=DEFAULT_SPEC,
                        help=f"the world: {world_spec_help()} (default: %(default)s)")  # fmt: skip
    parser.add_argument(
        "--method",
        default="mapex",
        choices=list(METHODS),
        help="default: %(default)s; the --robots of a run share one map, deployed about 1 m "
        "apart around the start",
    )
    add_budget_arguments(parser)
    add_start_argument(parser, 0, "start pose of the first run (default 0)")
    parser.add_argument(
        "--seed",
        type=argparse_type(parse_seed),
        default=0,
        help="seed of the first run (default 0)",
    )
    parser.add_argument(
        "--robots", type=int, default=1, help="robots of each run, one team (default 1)"
    )
    parser.add_argument("--runs", type=int, default=1, help="episodes run at once (default 1)")
    add_pool_arguments(parser)
    parser.add_argument(
        "--out", type=Path, default=None, help="results parent folder (default: as mapex run)"
    )
    parser.add_argument("--run-prefix", default=None, help="run ids are <prefix>-<k>")
    add_run_config_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_outside_tool_arguments(parser)
    add_zenoh_arguments(parser, HUB_HELP)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for flag in ("robots", "runs", "replicas", "threads"):
        if getattr(args, flag) < 1:
            parser.error(f"--{flag} must be at least 1")
    if args.seed + args.runs - 1 > MAX_SEED:
        parser.error(f"--seed {args.seed} + --runs {args.runs}: the seeds end above {MAX_SEED}")
    if args.run_prefix is not None and not (
        is_valid_id(args.run_prefix) and len(args.run_prefix) <= RUN_PREFIX_MAX_CHARS
    ):
        parser.error(f"--run-prefix must match [a-z0-9_-]{{1,{RUN_PREFIX_MAX_CHARS}}}")
    configure_logging("up")
    try:
        return main(args)
    except (WorldError, ConfigError, ZenohConfigError, ValueError, OSError) as error:
        print(f"services.up: error: {' '.join(str(error).split())}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    exit_on_signals()  # a signal before serving ends the process at once
    sys.exit(run_cli())
