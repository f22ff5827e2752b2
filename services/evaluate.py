"""`python -m services.evaluate`: the paper's experiment, every method x map x start x seed.

    python -m services.evaluate --maps DIR [DIR|generated:SEED ...] [--methods ...]
        [--ablations] [--starts 0,1,2,3 | --starts-file FILE] [--steps 1000] [--seeds 0]
        [--jobs 2] [--out results/evaluation] [--shard K/N] [--set SECTION.FIELD=VALUE ...]
        [--predictor lama|lama-v2|oracle] [Zenoh flags]

Runs every episode in a planner process of its own (`--jobs` at a time) on one shared
predictor pool, keeps each finished episode in `<out>` so that the same command resumes,
and writes the report to `<out>/report/`. `--shard K/N` runs the K-th (0-based) of N
slices of the episodes (`mapex.shards`), for clusters: docs/deploy.md. How it runs, resumes
and checks its input: docs/design.md#an-experiment-servicesevaluate.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import os
import shlex
import shutil
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from tqdm import tqdm

from mapex.budget import Steps, add_budget_arguments, resolve_steps
from mapex.config import (
    ConfigError,
    ExplorationConfig,
    WorldConfig,
    argparse_type,
    parse_seed,
)
from mapex.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from mapex.io_limits import read_text
from mapex.methods import (
    ABLATIONS,
    MAIN_COMPARISON,
    TEAM_METHODS,
    parse_method_list,
    records_team,
)
from mapex.prediction import DEFAULT_PREDICTOR, ORACLE, ORACLE_NOTICE
from mapex.prediction.config import inference_from_args
from mapex.report.runs import ReportError, load_run
from mapex.results import (
    METRICS_FILE,
    campaign_record,
    check_output_folder,
    claim_campaign,
    config_difference,
    episode_name,
    method_label,
    move_into_place,
)
from mapex.shards import Shard, parse_shard, shard_items
from mapex.worlds import StartSpec, WorldError, load_world, world_spec_help
from mapex.worlds.starts import start_argument, start_cells, start_label
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
from services.keys import ID_MAX_CHARS
from services.messages import MetricsMessage
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
from services.serving import configure_logging, exit_on_signals, stop_on_signals
from services.supervisor import ProcessSpec, Supervisor
from services.zenoh_config import HUB_HELP, ZenohConfigError, add_zenoh_arguments, open_session

DEFAULT_OUT = Path("results/evaluation")
DEFAULT_WORLD_CONFIG = WorldConfig()
BROKEN_DIR = ".broken"  # where a resume moves finished folders it cannot trust
RUN_LOG_FILE = "evaluations.jsonl"  # one line per invocation: command, runs, wall time

log = logging.getLogger("services.evaluate")


@dataclass(frozen=True)
class Episode:
    """One run of the experiment; `name` is its results folder (as `mapex.results.run_name`)."""

    world_spec: str
    world_name: str
    method: str
    start: StartSpec
    seed: int
    robots: int = 1  # a team method's team size
    steps: int = 1000  # the time budget T on this world (`--steps auto` differs per world)
    predictor: str = DEFAULT_PREDICTOR

    @property
    def name(self) -> str:
        return episode_name(
            self.world_name, self.method, self.start, self.seed, self.robots, self.predictor
        )

    @property
    def label(self) -> str:
        """The method as its folder and the report name it (`mapex@oracle`)."""
        return method_label(self.method, self.predictor)

    @property
    def run_id(self) -> str:
        """A key-safe run id (lower case, at most ID_MAX_CHARS)."""
        safe = "".join(c if c.isalnum() or c in "_-" else "_" for c in self.name.lower())
        return safe[-ID_MAX_CHARS:]


def plan_episodes(
    world_specs: list[str],
    methods: list[str],
    starts: list[int] | dict[str, list[StartSpec]],
    seeds: list[int],
    world_config: WorldConfig = DEFAULT_WORLD_CONFIG,
    robots: int = 1,
    steps: Steps = 1000,
    predictor: str = DEFAULT_PREDICTOR,
) -> list[Episode]:
    """Every combination, worlds outermost. `starts`: the corners for every map, or each
    map's own starts by map name (see `read_starts_file`). Loads each world once to name
    it and to check its size and every start on it (WorldError naming map and cell).
    `robots`: the team size of the team methods (single-robot methods run alone); `steps`:
    the budget, or None for each world's `auto` budget; `predictor`: every episode's."""
    episodes = []
    for spec in world_specs:
        world = load_world(spec, world_config.max_cells)
        mine = starts if isinstance(starts, list) else _starts_of(starts, world.name)
        start_cells(world, mine, world_config.start_clearance_cells)  # all at once
        budget = resolve_steps(steps, world)
        episodes += [
            Episode(
                spec,
                world.name,
                method,
                start,
                seed,
                robots if method in TEAM_METHODS else 1,
                budget,
                predictor,
            )  # fmt: skip
            for method, start, seed in itertools.product(methods, mine, seeds)
        ]
    return episodes


def _starts_of(starts: dict[str, list[StartSpec]], world_name: str) -> list[StartSpec]:
    if world_name not in starts:
        raise WorldError(f"the starts file names no starts for map '{world_name}'")
    return starts[world_name]


def read_starts_file(
    path: Path,
    max_bytes: int = DEFAULT_WORLD_CONFIG.max_file_bytes,
    world: WorldConfig = DEFAULT_WORLD_CONFIG,
) -> dict[str, list[StartSpec]]:
    """{map name: [(row, col), ...]} from a JSON object of [[row, col], ...] lists; a
    one-line ValueError for anything else (a file that is not a regular file, or larger
    than `max_bytes`, is never read: `mapex.io_limits`). More than `world.max_starts`
    starts, all maps together, is a ConfigError naming the cap, raised as soon as the
    parser reads a number past them (two a start): a file of millions is never parsed whole."""
    numbers = itertools.count(1)

    def counted(kind: type) -> Callable[[str], int | float]:
        def parse(text: str) -> int | float:
            if next(numbers) > 2 * world.max_starts:
                raise ConfigError(world.too_many_starts(f"starts file {path}"))
            return kind(text)

        return parse

    try:
        data = json.loads(
            read_text(path, max_bytes), parse_int=counted(int), parse_float=counted(float)
        )
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as error:
        raise ValueError(f"starts file {path}: {' '.join(str(error).split())}") from None
    if not isinstance(data, dict):
        raise ValueError(f"starts file {path}: expected a JSON object of map name -> starts")
    starts = {}
    for name, cells in data.items():
        if not (isinstance(cells, list) and cells and all(_is_cell(c) for c in cells)):
            raise ValueError(
                f"starts file {path}: map '{name}' needs a non-empty list of [row, col] cells"
            )
        starts[name] = [(int(c[0]), int(c[1])) for c in cells]
    return starts


def _is_cell(value) -> bool:
    return (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value)
    )


def plain_config(exploration: ExplorationConfig, episode: Episode) -> dict:
    """The configuration `episode` runs with, as the plain data metrics.json records."""
    return json.loads(json.dumps(asdict(replace(exploration, steps=episode.steps))))


def finished(episode: Episode, out_dir: Path, config: dict | None = None) -> bool:
    """Whether the episode has a sound results folder. Folders appear whole, by rename, but
    a disk, an editor or another version can still damage one: a folder that fails
    `run_problem` is moved aside to `<out>/.broken/` (named in the log) and run again."""
    folder = out_dir / episode.name
    if not folder.exists():
        return False
    problem = run_problem(episode, folder, config)
    if problem is None:
        return True
    aside = out_dir / BROKEN_DIR / f"{episode.name}-{time.strftime('%Y%m%dT%H%M%S')}"
    aside.parent.mkdir(exist_ok=True)
    folder.rename(aside)
    log.warning("%s: %s; moved aside to %s, running it again", episode.name, problem, aside)
    return False


def run_problem(episode: Episode, folder: Path, config: dict | None = None) -> str | None:
    """Why a finished folder cannot count for `episode`, or None: its metrics and curves must
    parse, name this world, method (with its predictor unless the default:
    `mapex.results.method_label`), start and seed, and (given `config`, the plain-data
    configuration the episode would run with) agree with it on every field both have."""
    try:
        record = load_run(folder)
    except (ReportError, OSError, ValueError, KeyError, TypeError) as error:
        return f"unreadable ({' '.join(str(error).split())})"
    wanted = (episode.world_name, episode.label, start_label(episode.start), episode.seed)
    found = (record.world, record.labelled_method, record.start, record.seed)
    if found != wanted:
        return f"it holds {'/'.join(map(str, found))}, not {'/'.join(map(str, wanted))}"
    if len(record.steps) == 0:
        return "its curves are empty"
    if "reached" not in record.metrics:
        return "it has no time-to-level record (written by an older version)"
    team = record.metrics.get("team") or {}
    if records_team(episode.method, episode.robots) and team.get("robots") != episode.robots:
        return f"it holds a team of {team.get('robots')}, not {episode.robots}"
    differing = config_difference(record.metrics.get("config"), config)
    return None if differing is None else f"it was run with another {differing}"


def planner_folder(episode: Episode, out_dir: Path) -> Path:
    """Where the episode's planner writes its results: hidden until `publish` renames it.

    Only a live evaluation publishes a run, so a planner orphaned by a kill (whose pool died
    with its supervisor, leaving its last metric samples degraded) can never add one.
    """
    return out_dir / f".{episode.name}.planner"


def publish(episode: Episode, out_dir: Path) -> bool:
    """Move the folder the episode's planner wrote to its results folder; whether it was there."""
    written = planner_folder(episode, out_dir)
    if not (written / METRICS_FILE).is_file():
        return False
    move_into_place(written, out_dir / episode.name)
    return True


def remove_staging(out_dir: Path, episodes: list[Episode] | None = None) -> int:
    """Delete half-written folders a kill left behind (names start with '.'); how many.
    Given `episodes` (a shard's, in a folder other shards may be writing to), only theirs:
    `.<name>.planner` and the planner's own staging `..<name>.planner.*`."""
    hidden = out_dir.glob(".*") if out_dir.is_dir() else []
    stale = [p for p in hidden if p.is_dir() and p.name != BROKEN_DIR]
    if episodes is not None:
        mine = {planner_folder(e, out_dir).name for e in episodes}
        stale = [p for p in stale if p.name in mine or p.name[1:].rsplit(".", 1)[0] in mine]
    for path in stale:
        shutil.rmtree(path, ignore_errors=True)
    return len(stale)


def planner_spec(
    episode: Episode, settings: list[str], out_dir: Path, flags: list[str]
) -> ProcessSpec:
    """The planner process of `episode`, with the run's `--set` items `settings`."""
    planner_args = [
        "--run", episode.run_id, "--world", episode.world_spec,
        "--start", start_argument(episode.start),
        "--method", episode.method, "--seed", str(episode.seed), "--steps", str(episode.steps),
        "--out", str(planner_folder(episode, out_dir)), "--no-progress",
        "--robots", str(episode.robots),
    ]  # fmt: skip
    if episode.predictor != DEFAULT_PREDICTOR:
        planner_args += ["--predictor", episode.predictor]
    for item in settings:
        planner_args += ["--set", item]
    return ProcessSpec(f"episode-{episode.run_id}", "services.planner", (*planner_args, *flags))


def run_episodes(
    supervisor: Supervisor,
    todo: list[Episode],
    args: argparse.Namespace,
    flags: list[str],
    progress: RunProgress,
    stop: threading.Event,
    watch: PoolWatch | None = None,
    settings: list[str] | None = None,
    hub: HubWatch | None = None,
) -> tuple[int, list[str]]:
    """Run `todo`, `args.jobs` at a time; (episodes finished, failure lines). `watch` kills
    stuck workers for the supervisor to restart; `settings`: the run's `--set` items; a
    joined hub that is gone (`hub`) ends the run as a failure.

    On `stop` no episode starts, and the planners that have exited cleanly by then (one may
    finish in the very poll the stop arrives in) are published before the caller stops the
    rest: a finished episode is never thrown away."""
    queue, running, done, failures = list(todo), {}, [], []
    bar = tqdm(
        total=sum(episode.steps for episode in todo),
        unit="step",
        file=sys.stderr,
        disable=args.no_progress,
        desc=f"{len(todo)} episodes",
    )
    with bar:
        while (queue or running) and not stop.is_set():
            supervisor.poll()
            if watch is not None:
                watch.check()
            if hub is not None and (lost := hub.lost()) is not None:
                failures.append(lost)
                break
            while queue and len(running) < args.jobs:
                episode = queue.pop(0)
                spec = planner_spec(episode, settings or [], args.out, flags)
                supervisor.start(spec)
                running[spec.name] = episode
            _collect_exited(supervisor, running, args.out, done, failures)
            steps = sum(e.steps for e in done) + sum(
                progress.of(e.run_id) for e in running.values()
            )
            bar.update(min(steps, bar.total) - bar.n)
            bar.set_postfix_str(f"{len(done)} done, {len(failures)} failed", refresh=False)
            time.sleep(supervisor.services.supervision_poll_s)
    if running:  # stopped: keep what finished cleanly before the rest is stopped
        supervisor.poll()
        _collect_exited(supervisor, running, args.out, done, failures)
    return len(done), failures


def _collect_exited(
    supervisor: Supervisor,
    running: dict[str, Episode],
    out_dir: Path,
    done: list[Episode],
    failures: list[str],
) -> None:
    """Move every planner of `running` that has exited out of it: a clean exit with its
    folder written is published into `done`, any other exit is a line in `failures`."""
    for name, episode in list(running.items()):
        code = supervisor.returncode(name)
        if code is None:
            continue
        del running[name]
        if code == 0 and publish(episode, out_dir):
            done.append(episode)
        else:
            failures.append(f"{episode.name}: planner exited with {code}")


def main(args: argparse.Namespace) -> int:
    began = time.monotonic()
    shard = None if args.shard is None else parse_shard(args.shard)
    run_config = RunConfig(ExplorationConfig(until_iou=args.until_iou))
    run_config = run_config.with_overrides(args.overrides)
    exploration, services = run_config.exploration, run_config.services
    methods = list(args.methods) + (list(ABLATIONS) if args.ablations else [])
    max_bytes = exploration.world.max_file_bytes
    if args.starts_file is None:
        exploration.world.check_starts(len(args.starts), "--starts")
        starts = args.starts
    else:
        starts = read_starts_file(args.starts_file, max_bytes, exploration.world)
    exploration.team.check_robots(args.robots)
    resolve_pool_predictor(args)
    if args.robots > 1 and not any(method in TEAM_METHODS for method in methods):
        raise ConfigError(f"--robots {args.robots} needs a team method ({', '.join(TEAM_METHODS)})")
    bridges = tool_process_count(args)
    services.check_processes(
        args.jobs + len(args.members) * args.replicas + bridges,
        f"--jobs {args.jobs} planners and {len(args.members)} x --replicas {args.replicas} "
        f"workers" + (f" and {bridges} outside tools" if bridges else ""),
    )
    episodes = plan_episodes(
        args.maps, methods, starts, args.seeds, exploration.world, args.robots, args.steps,
        args.predictor,
    )  # fmt: skip
    check_output_folder(args.out)
    check_outside_tool_arguments(args)
    mine = episodes if shard is None else shard_items(episodes, shard, lambda e: e.method)
    every = {e.name: e.steps for e in episodes}
    plain = plain_config(exploration, episodes[0])
    claim_campaign(args.out, campaign_record(every, plain, 1 if shard is None else shard.count))
    if remove_staging(args.out, None if shard is None else mine):
        log.info("removed half-written runs of an interrupted evaluation")
    todo = [e for e in mine if not finished(e, args.out, plain_config(exploration, e))]
    already = len(mine) - len(todo)
    whose = "" if shard is None else f"shard {shard}: {len(mine)} of the "
    counts = (len(episodes), already, len(todo))
    log.info("%s%d episodes: %d already finished, %d to run", whose, *counts)
    connect_file = adopt_config_file(args)  # a --config file's mode and endpoints count
    check_hub_answers(args.connect, services, connect_file)
    if shard is not None and not (args.listen or args.connect):
        args.listen = [free_hub_endpoint()]  # shards on one machine serve a hub each
        log.info("shard %s serves its hub on %s", shard, args.listen[0])
    own_config, flags = hub_session_config(args, services)
    stop = stop_on_signals()
    session = open_session(own_config)
    progress = RunProgress(session, "metrics", MetricsMessage)
    supervisor = Supervisor(services=services)
    workers = worker_specs(
        args.members,
        args.replicas,
        args.threads,
        flags,
        inference_from_args(args),
        id_prefix=f"ev{os.getpid()}" + ("" if shard is None else f"s{shard.index}"),
        settings=run_config.as_overrides(),
        predictor=args.predictor,
    )
    if args.predictor == ORACLE:
        log.warning("%s", ORACLE_NOTICE)
    watch = PoolWatch(session, supervisor, workers, services)
    tools = None
    try:
        tools = OutsideTools(session, args)
        if todo:
            for spec in bridge_spec(args, flags) + viewer_specs(args, flags) + workers:
                supervisor.start(spec)
        hub = HubWatch(session, args.connect, services)
        done, failures = run_episodes(
            supervisor, todo, args, flags, progress, stop, watch, run_config.as_overrides(), hub
        )
    finally:
        if tools is not None:
            tools.close()
        supervisor.stop()
        progress.close()
        session.close()
    wall_s = time.monotonic() - began
    _log_invocation(args, len(episodes), done, failures, wall_s, stop.is_set(), shard)
    if stop.is_set():
        print(f"interrupted after {done} episodes; rerun to resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    for line in failures:
        log.error("%s", line)
    print(f"{done} episodes run in {wall_s / 60:.1f} min -> {args.out}", file=sys.stderr)
    if shard is not None:  # the report needs every shard: mapex.report merges their folders
        merge = f"python -m mapex.report {args.out} [the other shards' folders]"
        print(f"shard {shard}: once all {shard.count} are done, {merge}", file=sys.stderr)
    elif not args.no_report:
        from mapex.report import main as report_main

        if report_main([str(args.out)]) != 0:
            return EXIT_FAILED
    return EXIT_FAILED if failures else 0


def _log_invocation(
    args: argparse.Namespace,
    total: int,
    done: int,
    failures: list[str],
    wall_s: float,
    interrupted: bool,
    shard: Shard | None = None,
) -> None:
    record = {
        "command": "python -m services.evaluate " + shlex.join(sys.argv[1:]),
        **({} if shard is None else {"shard": str(shard)}),
        "episodes": total,
        "ran": done,
        "failed": len(failures),
        "interrupted": interrupted,
        "wall_time_s": round(wall_s, 1),
        "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    with (args.out / RUN_LOG_FILE).open("a") as handle:
        handle.write(json.dumps(record) + "\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.evaluate", description=__doc__.split("\n\n")[2].strip()
    )
    parser.add_argument(
        "--maps",
        nargs="+",
        required=True,
        metavar="MAP",
        help=f"the worlds, each {world_spec_help()}",
    )
    parser.add_argument(
        "--methods",
        type=argparse_type(lambda text: parse_method_list(text)),
        default=list(MAIN_COMPARISON),
        help="comma-separated (default: "
        + ",".join(MAIN_COMPARISON)
        + "); the team methods ("
        + ",".join(TEAM_METHODS)
        + ") run teams of --robots, the others alone",
    )
    parser.add_argument(
        "--robots", type=int, default=1, help="team size of the team methods (default 1)"
    )
    parser.add_argument(
        "--ablations", action="store_true", help="add the ablations " + ",".join(ABLATIONS)
    )
    parser.add_argument(
        "--starts", type=_ints, default=[0, 1, 2, 3], help="corners 0-3 (default: 0,1,2,3)"
    )
    parser.add_argument(
        "--starts-file",
        type=Path,
        default=None,
        metavar="FILE",
        help='explicit starts instead of corners: JSON {"<map name>": [[row, col], ...]}, '
        f"at most world.max_starts ({DEFAULT_WORLD_CONFIG.max_starts}) of them, all maps together",
    )
    parser.add_argument(
        "--seeds", type=_seeds, default=[0], help="comma-separated seeds (default: 0)"
    )
    add_budget_arguments(parser)
    parser.add_argument("--jobs", type=int, default=2, help="episodes at once (default 2)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="default: %(default)s")
    parser.add_argument(
        "--shard",
        default=None,
        metavar="K/N",
        help="run only shard K (0-based: $SLURM_ARRAY_TASK_ID, $JOB_COMPLETION_INDEX) of N "
        "balanced slices of the episodes, into its own or a shared --out, without the report "
        "(python -m mapex.report merges the shards' folders); docs/deploy.md",
    )
    add_run_config_argument(parser)
    add_pool_arguments(parser)
    parser.add_argument("--no-report", action="store_true", help="skip the report at the end")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_outside_tool_arguments(parser)
    add_zenoh_arguments(parser, HUB_HELP)
    return parser


def free_hub_endpoint() -> str:
    """A loopback endpoint on a port that is free now, for a shard's own hub: shards that
    share a machine (tasks of a Slurm array on one node) then never meet."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def _seeds(text: str) -> list[int]:
    try:
        return [parse_seed(item.strip()) for item in text.split(",")]
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _ints(text: str) -> list[int]:
    items = text.split(",")
    if not all(item.strip().isdigit() for item in items):
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of integers")
    return [int(item) for item in items]


def run_cli(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for flag in ("jobs", "replicas", "threads"):
        if getattr(args, flag) < 1:
            parser.error(f"--{flag} must be at least 1")
    if any(start > 3 for start in args.starts):
        parser.error("--starts are start poses 0-3")
    configure_logging("evaluate")
    try:
        return main(args)
    except (WorldError, ConfigError, ZenohConfigError, ValueError, OSError) as error:
        print(f"services.evaluate: error: {' '.join(str(error).split())}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    exit_on_signals()  # a signal before serving ends the process at once
    sys.exit(run_cli())
