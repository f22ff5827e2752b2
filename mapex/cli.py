"""`python -m mapex`: run exploration episodes from the command line."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from mapex.budget import add_budget_arguments, resolve_steps
from mapex.config import (
    ConfigError,
    ExplorationConfig,
    add_override_argument,
    apply_overrides,
    argparse_type,
    parse_seed,
)
from mapex.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from mapex.methods import METHODS
from mapex.prediction import (
    ORACLE,
    ORACLE_NOTICE,
    add_predictor_argument,
    inference_options,
    make_predictor,
)
from mapex.prediction.config import add_inference_arguments, inference_from_args
from mapex.prediction.weights import WeightsError
from mapex.worlds import DEFAULT_WORLD, WorldError, load_world, start_label, world_spec_help
from mapex.worlds.starts import add_start_argument


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m mapex",
        description="MapEx exploration simulator, in one process (docs/algorithms.md).",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser(
        "run",
        help="run one exploration episode and write its results folder",
        description="Explore a world with one method for a number of steps; writes metrics.json, "
        "curves.csv, trajectory.csv and final.png to the results folder.",
    )
    run.add_argument(
        "--world",
        default=DEFAULT_WORLD,
        help=f"the world: {world_spec_help()}; default: %(default)s",
    )
    run.add_argument(
        "--method",
        default="mapex",
        choices=list(METHODS),
        help="default: %(default)s; in a team (--robots > 1) the methods that coordinate ("
        + ", ".join(n for n, m in METHODS.items() if m.coordinates)
        + ") share goals, the others run independently on the shared map",
    )
    run.add_argument(
        "--robots",
        type=int,
        default=1,
        help="robots sharing one map (default 1); a team deploys about 1 m apart around the "
        "start (docs/algorithms.md#teams)",
    )
    add_predictor_argument(run)
    add_inference_arguments(run)
    add_budget_arguments(run)
    add_start_argument(run, 0, "start pose (default 0)")
    run.add_argument(
        "--seed",
        type=argparse_type(parse_seed),
        default=0,
        help="random seed (UPEN's RRT), an integer >= 0; default: 0",
    )
    run.add_argument(
        "--out", type=Path, default=None, help="results folder; default: results/<run name>"
    )
    run.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="FILE.mcap",
        help="also write the run as a rosbag2 bag in one MCAP file (ROS 2 topics, CDR: "
        "`ros2 bag play`, rosbags, Foxglove, Lichtblick; needs the ros extra)",
    )
    run.add_argument(
        "--record-foxglove",
        type=Path,
        default=None,
        metavar="FILE.mcap",
        help="also write the run's Foxglove channels (protobuf foxglove.Grid, PoseInFrame, "
        "PosesInFrame) as an MCAP file of their own (needs the ros extra)",
    )
    add_override_argument(run)
    run.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def predictor_options(args: argparse.Namespace) -> dict:
    """Keyword arguments of the chosen predictor from the flags (only the learned ones take
    the inference flags; ConfigError, one line, when another is given changed ones)."""
    return inference_options(args.predictor, inference_from_args(args))


def _open_recording(args: argparse.Namespace, world, method: str):
    """The run's MCAP recordings (--record, --record-foxglove), or None without either
    (ConfigError, one line, when the ros extra is missing or a file cannot be written)."""
    paths = {"--record": args.record, "--record-foxglove": args.record_foxglove}
    if args.record is None and args.record_foxglove is None:
        return None
    from mapex.interop.episode_recording import EpisodeRecording
    from mapex.interop.mcap_file import recording_flags_problem
    from mapex.interop.ros_messages import MissingExtraError

    if (problem := recording_flags_problem(paths)) is not None:
        raise ConfigError(problem)
    flags = " / ".join(flag for flag, path in paths.items() if path is not None)
    try:
        return EpisodeRecording(
            args.record, f"{world.name}_{method}", world.shape, world.resolution_m,
            foxglove_path=args.record_foxglove,
        )  # fmt: skip
    except (MissingExtraError, OSError) as error:
        raise ConfigError(f"{flags}: {error}") from None


def run_command(args: argparse.Namespace) -> int:
    from mapex.episode import run_episode
    from mapex.results import (
        OutputError,
        check_destination,
        describe_end,
        destination,
        write_results,
    )
    from mapex.team.starts import team_start_cells

    config = apply_overrides(ExplorationConfig(until_iou=args.until_iou), args.overrides)
    config.team.check_robots(args.robots)
    world = load_world(args.world, config.world.max_cells)
    config = replace(config, steps=resolve_steps(args.steps, world))
    team_start_cells(world, [args.start], args.robots, config)  # a bad start: no work
    check_destination(args.out)
    recording = _open_recording(args, world, args.method)
    predictor = make_predictor(args.predictor, world.occupancy, **predictor_options(args))
    if args.predictor == ORACLE:
        print(f"mapex: {ORACLE_NOTICE}", file=sys.stderr)
    with tqdm(
        total=config.steps,
        desc=f"{args.method} on {world.name}",
        unit="step",
        disable=args.no_progress,
        file=sys.stderr,
    ) as bar:

        def progress(t: int, explorers, _recorder) -> None:
            bar.update(t - bar.n)
            if recording is not None:
                recording.step(t, explorers)

        try:
            result = run_episode(
                world, args.method, predictor, args.start, args.seed, config,
                on_step=progress, robots=args.robots,
            )  # fmt: skip
        finally:
            if recording is not None:
                print(f"recorded {recording.close()}", file=sys.stderr)
    out_dir = destination(args.out, result)
    try:
        write_results(result, world, out_dir)
    except OutputError as error:
        print(f"mapex: error: {error}", file=sys.stderr)
        return EXIT_FAILED
    auc = result.curves.auc()
    if result.is_team:
        lengths = ", ".join(f"{length:.1f}" for length in result.path_lengths_m)
        print(f"team of {result.robots}: overlap {result.overlap:.3f}, paths {lengths} m")
    print(
        f"{result.method} on {result.world} ({start_label(result.start_spec)}): coverage AUC "
        f"{auc['coverage']:.3f}, IoU AUC {auc['iou']:.3f}, TU AUC {auc['tu']:.3f}, "
        f"final coverage {result.curves.coverage[-1]:.3f}, {describe_end(result)} -> {out_dir}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run_command(args)
    except (WorldError, ConfigError, WeightsError, OSError) as error:
        print(f"mapex: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("mapex: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
