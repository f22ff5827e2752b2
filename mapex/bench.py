"""`python -m mapex.bench`: speed figures of the exploration core (medians, milliseconds).

Measures, on one map (default: the largest development map, KTH 50015847):
one LiDAR scan + integration; scoring 30 frontiers with `mapex`; one A* across
the map; the learned ensemble (the network's multiply-adds, the GFLOP/s reached against
one core's measured matrix-product peak); one whole re-plan of `mapex` and `mapex_plus`; a
full `nearest` episode. The ensemble's figures are printed for the inference path before
issue #50 (plain PyTorch module, two views) beside today's. Prints each median next to its
target.
Benchmarks print figures; they never fail a test run.
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
import statistics
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from mapex.config import ExplorationConfig
from mapex.episode import run_episode
from mapex.exit_codes import EXIT_USAGE
from mapex.explorer import Explorer
from mapex.frontiers import extract_frontiers
from mapex.grid import FREE, new_observed_map
from mapex.methods import PlanningContext, make_method
from mapex.navigation import cost_map, plan_path, reachable_mask
from mapex.prediction import DEFAULT_PREDICTOR, make_predictor
from mapex.prediction.base import EnsemblePrediction
from mapex.sensor import cast_scan, integrate_scan, scan_and_integrate
from mapex.simulator import Simulator
from mapex.worlds import WorldError, load_world, start_poses, world_spec_help

DEFAULT_MAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "kth_dev" / "50015847"
TARGETS_MS = {
    "scan + integration": 2.0,
    "score 30 frontiers (mapex)": 20.0,
    "nearest episode": 15000.0,
    "one member, whole map, 1 thread": 100.0,
    "four members, whole map, 2 processes": 250.0,
    "re-plan with prediction (mapex_plus)": 1000.0,
    "nearest episode, lama": 4000.0,
}


def median_ms(action: Callable[[], object], repeats: int) -> float:
    """Median wall time of `action` in ms over `repeats` calls (after one warm-up call)."""
    action()
    times = []
    for _ in range(repeats):
        began = time.perf_counter()
        action()
        times.append((time.perf_counter() - began) * 1e3)
    return statistics.median(times)


def report(name: str, value_ms: float, detail: str = "") -> None:
    target = TARGETS_MS.get(name)
    verdict = ""
    if target is not None:
        verdict = f"  target <= {target:g} ms: {'met' if value_ms <= target else 'MISSED'}"
    print(f"{name:<44} {value_ms:10.2f} ms{verdict}{('  ' + detail) if detail else ''}", flush=True)


def bench_scan(world, config: ExplorationConfig, repeats: int) -> None:
    free = np.argwhere(~world.occupancy & world.valid_space)
    poses = [tuple(int(v) for v in free[i]) for i in np.random.default_rng(0).choice(len(free), 50)]
    observed = new_observed_map(world.shape)
    cycle = iter(poses * (repeats + 1))

    def fused() -> None:
        scan_and_integrate(world.occupancy, observed, next(cycle), config.sensor)

    def split() -> None:
        integrate_scan(
            observed, cast_scan(world.occupancy, next(cycle), config.sensor), config.sensor
        )

    report("scan + integration", median_ms(fused, repeats), "(fused, in-process path)")
    report("scan, then integration", median_ms(split, repeats), "(as sent over the network)")


def explored_state(world, config: ExplorationConfig, steps: int) -> Explorer:
    """An explorer part-way through a nearest-frontier run (a realistic scoring situation)."""
    start = start_poses(world, config.world.start_clearance_cells)[0]
    simulator = Simulator(world, [start], config.sensor, config.motion)
    explorer = Explorer(world.shape, make_method("nearest", config), None, config, seed=0)
    explorer.observe(simulator.scan(0))
    for t in range(steps):
        motion = explorer.next_motion(t)
        if motion is None:
            break
        explorer.observe(simulator.step(0, motion))
    return explorer


def bench_scoring(world, config: ExplorationConfig, repeats: int) -> None:
    explorer = explored_state(world, config, steps=300)
    observed = explorer.observed
    frontiers = extract_frontiers(observed, config.frontier)
    free = np.argwhere(observed == FREE)
    extra = free[np.random.default_rng(1).choice(len(free), max(30 - len(frontiers), 0))]
    points = np.concatenate([frontiers, extra])[:30]
    predictor = make_predictor("classical")
    explorer.predictor = predictor
    prediction = explorer.predict()  # known area + sensor range, as the explorer does
    cost = cost_map(observed, config.navigation)
    context = PlanningContext(
        observed=observed,
        pose=explorer.pose,
        frontiers=points,
        prediction=prediction,
        cost=cost,
        reachable=reachable_mask(cost, tuple(int(v) for v in explorer.pose)),
        config=config,
        rng=np.random.default_rng(0),
    )
    mapex = make_method("mapex", config)

    def score_fresh() -> None:
        """Score with a fresh ensemble so the mean and variance maps are computed each time."""
        fresh = EnsemblePrediction(prediction.members, prediction.region)
        mapex.score(dataclasses.replace(context, prediction=fresh))

    report(
        "score 30 frontiers (mapex)",
        median_ms(score_fresh, repeats),
        f"({len(frontiers)} real frontiers, stop rule {config.visibility.stop_rule})",
    )
    report(
        "extract frontiers",
        median_ms(lambda: extract_frontiers(observed, config.frontier), repeats),
    )
    report("planning cost map", median_ms(lambda: cost_map(observed, config.navigation), repeats))
    report("classical ensemble, known+range", median_ms(explorer.predict, 5))


def bench_astar(world, config: ExplorationConfig, repeats: int) -> None:
    observed = np.where(world.occupancy, np.uint8(2), FREE).astype(np.uint8)
    cost = cost_map(observed, config.navigation)
    starts = start_poses(world, config.world.start_clearance_cells)
    a, b = starts[0], starts[3]
    path = plan_path(observed, cost, a, b)
    length = 0 if path is None else len(path)
    report(
        "A* across the map",
        median_ms(lambda: plan_path(observed, cost, a, b), repeats),
        f"({a} -> {b}, {length} cells)",
    )


_worker_ensemble = None  # the ensemble a benchmark worker process loaded (one per process)

# The inference path before issue #50 (the training module, two views) and the paths of now.
OLD_PATH = {"inference": "plain", "views": 2}
PATHS = {
    "old path: plain, two views": OLD_PATH,
    "fused, two views (default)": {},
    "fused, one view (--views 1)": {"views": 1},
}


def _load_worker_ensemble(options: dict) -> None:
    """Pool initializer: one torch thread and the shipped ensemble, once per process."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble

    global _worker_ensemble
    torch.set_num_threads(1)
    _worker_ensemble = LearnedEnsemble(recent_answers=0, **options)


def _predict_member(observed: np.ndarray, member: int) -> np.ndarray:
    return _worker_ensemble.predict_members(observed, (member,))


def network_flops(observed: np.ndarray) -> int:
    """Floating-point operations (2 per multiply-add) of one forward pass of the shipped
    network on `observed`, by torch's flop counter (convolutions and matrix products; the
    FFTs' few MFLOP are not counted)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from mapex.prediction.network import encode_observed
    from mapex.prediction.weights import WEIGHTS_DIR, load_member

    model = load_member(WEIGHTS_DIR / "g.pt")
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        model(torch.from_numpy(encode_observed(observed))[None])
    return counter.get_total_flops()


def core_peak_gflops(size: int = 2048, repeats: int = 5) -> float:
    """What one core reaches on a large float32 matrix product (torch.mm, one thread): the
    practical peak the network's GFLOP/s are set against."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    a, b = torch.randn(size, size), torch.randn(size, size)
    ms = median_ms(lambda: torch.mm(a, b), repeats)
    torch.set_num_threads(threads)
    return 2 * size**3 / (ms * 1e6)


def profile_member(observed: np.ndarray, rows: int = 12) -> None:
    """Where one member's whole-map prediction (default path, one thread) spends its time:
    torch's profiler, operators grouped by input shape, the most expensive first."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble

    predictor = LearnedEnsemble(members=("g",), recent_answers=0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    predictor.predict_members(observed, (0,))
    with torch.profiler.profile(record_shapes=True) as profile:
        predictor.predict_members(observed, (0,))
    torch.set_num_threads(threads)
    table = profile.key_averages(group_by_input_shape=True).table(
        sort_by="self_cpu_time_total", row_limit=rows, max_name_column_width=28
    )
    print(table, flush=True)


def bench_learned(world, repeats: int, profile: bool = False) -> None:
    """The learned ensemble on the whole map, the old path beside the new ones: one member
    on one thread (the target); all four in two worker processes of one thread each (one
    per core, as the services' predictor pool runs them; the target); one member in
    bfloat16 (`--precision bfloat16`, no target). With the network's multiply-adds and the
    GFLOP/s reached against one core's measured matrix-product peak."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble

    observed = explored_state(world, ExplorationConfig(), steps=300).observed
    flops = network_flops(observed)
    peak = core_peak_gflops()
    print(
        f"network: {flops / 2e9:.2f} G multiply-adds ({flops / 1e9:.2f} GFLOP) per pass on "
        f"{observed.shape[0]} x {observed.shape[1]}; one core's float32 matrix-product peak "
        f"(torch.mm 2048^2, 1 thread): {peak:.0f} GFLOP/s",
        flush=True,
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    for label, options in PATHS.items():
        predictor = LearnedEnsemble(recent_answers=0, **options)
        passes = 2 if predictor.models[0].config.average_turned_view else 1
        one = median_ms(lambda p=predictor: p.predict_members(observed, (0,)), repeats)
        rate = passes * flops / (one * 1e6)
        name = "one member, whole map, 1 thread"
        report(name, one, f"[{label}] {rate:.0f} GFLOP/s, {100 * rate / peak:.0f} % of peak")
    bf16 = LearnedEnsemble(recent_answers=0, precision="bfloat16")
    one = median_ms(lambda: bf16.predict_members(observed, (0,)), repeats)
    report("one member, whole map, 1 thread, bfloat16", one, "[fused, two views]")
    torch.set_num_threads(threads)
    if profile:
        profile_member(observed)
    context = multiprocessing.get_context("spawn")
    for label, options in PATHS.items():
        with ProcessPoolExecutor(
            2, mp_context=context, initializer=_load_worker_ensemble, initargs=(options,)
        ) as pool:

            def four_in_processes() -> None:
                list(pool.map(_predict_member, [observed] * 4, range(4)))

            report(
                "four members, whole map, 2 processes",
                median_ms(four_in_processes, repeats),
                f"[{label}] 1 thread each",
            )


def bench_candidates(world, repeats: int, weights_dirs: list[Path]) -> None:
    """Each trained ensemble in `weights_dirs` (e.g. candidate network sizes): its network's
    size and one member's whole-map prediction on one thread (default inference path), the
    time a predictor worker spends per query."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble
    from mapex.prediction.weights import load_member

    observed = explored_state(world, ExplorationConfig(), steps=300).observed
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    for directory in weights_dirs:
        model = load_member(directory / "g.pt")
        size = f"{model.config.channels} channels, {model.config.n_blocks} blocks"
        parameters = sum(p.numel() for p in model.parameters())
        predictor = LearnedEnsemble(directory, members=("g",), recent_answers=0)
        one = median_ms(lambda p=predictor: p.predict_members(observed, (0,)), repeats)
        report(
            "one member, whole map, 1 thread",
            one,
            f"[{directory}: {size}, {parameters / 1e6:.2f} M parameters]",
        )
    torch.set_num_threads(threads)


def bench_replan(world, config: ExplorationConfig, repeats: int, method_name: str) -> None:
    """One whole re-plan of `method_name` part-way through a run (t = 300): the learned
    ensemble on the known area plus sensor range (in process, two threads, as `python -m
    mapex run`), frontier clusters, cost map, reachability, scoring and the path to the goal;
    the old inference path, the default one, and the default in bfloat16."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble

    explorer = explored_state(world, config, steps=300)
    explorer.method = make_method(method_name, config)
    threads = torch.get_num_threads()
    for label, options in {
        "old path": OLD_PATH,
        "default": {},
        "default, bfloat16": {"precision": "bfloat16"},
    }.items():
        explorer.predictor = LearnedEnsemble(threads=2, recent_answers=0, **options)
        report(
            f"re-plan with prediction ({method_name})",
            median_ms(lambda: explorer.replan(300), repeats),
            f"[{label}] ({len(explorer.frontiers)} frontiers, t = 300)",
        )
    torch.set_num_threads(threads)


def bench_episode(
    world, config: ExplorationConfig, repeats: int, predictor_name: str, label: str = "", **options
) -> None:
    """A whole `nearest` episode as `python -m mapex run` runs it; the predictor only serves
    the IoU/TU metrics (G's whole-map prediction every 50 steps)."""
    predictor = make_predictor(predictor_name, **options)
    times = []
    for _ in range(repeats):
        result = run_episode(world, "nearest", predictor, 0, 0, config)
        times.append(result.wall_time_s * 1e3)
    predictor.close()
    name = "nearest episode"  # the target line (metrics with the classical predictor)
    if predictor_name != "classical":
        name = f"nearest episode, {predictor_name}"
    report(
        name,
        statistics.median(times),
        f"{label}({config.steps} steps incl. metrics with '{predictor_name}', median of "
        f"{repeats}; {statistics.median(times) / config.steps:.1f} ms/step)",
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mapex.bench", description=__doc__)
    parser.add_argument(
        "--world",
        default=str(DEFAULT_MAP),
        help=f"the world: {world_spec_help()}; default: %(default)s",
    )
    parser.add_argument("--repeats", type=int, default=50, help="repeats of the small benchmarks")
    parser.add_argument("--episodes", type=int, default=3, help="repeats of the episode benchmark")
    parser.add_argument("--steps", type=int, default=1000, help="episode length")
    parser.add_argument(
        "--profile", action="store_true", help="also print where one member's prediction spends"
    )
    parser.add_argument(
        "--candidates",
        nargs="+",
        type=Path,
        default=None,
        metavar="WEIGHTS_DIR",
        help="only time one member of each of these trained ensembles (folders written by "
        "mapex.training.train --out), e.g. network sizes being compared",
    )
    args = parser.parse_args(argv)
    try:
        world = load_world(args.world)
    except WorldError as error:
        print(f"mapex.bench: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    config = ExplorationConfig(steps=args.steps)
    print(f"map {world.name}: {world.shape[0]} x {world.shape[1]} cells; medians in ms", flush=True)
    if args.candidates:
        from mapex.prediction.weights import WeightsError  # torch only when asked

        try:
            bench_candidates(world, max(args.repeats // 10, 3), args.candidates)
        except WeightsError as error:
            print(f"mapex.bench: error: {error}", file=sys.stderr)
            return EXIT_USAGE
        return 0
    bench_scan(world, config, args.repeats)
    bench_scoring(world, config, args.repeats)
    bench_astar(world, config, max(args.repeats // 5, 3))
    bench_learned(world, max(args.repeats // 10, 3), args.profile)
    for method_name in ("mapex", "mapex_plus"):
        bench_replan(world, config, max(args.repeats // 10, 3), method_name)
    if args.episodes > 0:
        bench_episode(world, config, args.episodes, "classical")
        bench_episode(world, config, args.episodes, "lama", "[old path] ", **OLD_PATH)
        bench_episode(world, config, args.episodes, DEFAULT_PREDICTOR, "[default] ")
    return 0


if __name__ == "__main__":
    sys.exit(main())
