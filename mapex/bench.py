"""`python -m mapex.bench`: speed figures of the exploration core (medians, milliseconds).

Measures, on one map (default: the largest development map, KTH 50015847):
one LiDAR scan + integration; scoring 30 frontiers with `mapex`; one A* across
the map; the learned ensemble; one whole re-plan of `mapex` and `mapex_plus`; a full
`nearest` episode. Prints each median next to its target.
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
from mapex.prediction.config import PRECISIONS
from mapex.sensor import cast_scan, integrate_scan, scan_and_integrate
from mapex.simulator import Simulator
from mapex.worlds import WorldError, load_world, start_poses

DEFAULT_MAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "kth_dev" / "50015847"
TARGETS_MS = {
    "scan + integration": 2.0,
    "score 30 frontiers (mapex)": 20.0,
    "nearest episode": 15000.0,
    "one member, whole map, 1 thread": 800.0,
    "four members, whole map, 2 processes": 1500.0,
    "re-plan with prediction (mapex_plus)": 1000.0,
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


def _load_worker_ensemble() -> None:
    """Pool initializer: one torch thread and the shipped ensemble, once per process."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble

    global _worker_ensemble
    torch.set_num_threads(1)
    _worker_ensemble = LearnedEnsemble()


def _predict_member(observed: np.ndarray, member: int) -> np.ndarray:
    return _worker_ensemble.predict_members(observed, (member,))


def bench_learned(world, repeats: int) -> None:
    """The learned ensemble on the whole map: one member on one thread; all four in two
    worker processes of one thread each (one per core, as the services' predictor pool runs
    them; the target), and in one process on two threads; in float32 (the targets) and one
    member in bfloat16 (`--precision bfloat16`, no target)."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble

    observed = explored_state(world, ExplorationConfig(), steps=300).observed
    threads = torch.get_num_threads()
    predictors = {precision: LearnedEnsemble(precision=precision) for precision in PRECISIONS}
    torch.set_num_threads(1)
    for precision, predictor in predictors.items():
        suffix = "" if precision == "float32" else f", {precision}"
        one = median_ms(lambda p=predictor: p.predict_members(observed, (0,)), repeats)
        report(f"one member, whole map, 1 thread{suffix}", one)
    torch.set_num_threads(2)
    in_one_process = predictors["float32"]
    four = median_ms(lambda: in_one_process.predict_members(observed, range(4)), repeats)
    report("four members, whole map, 2 threads", four, "(one process)")
    torch.set_num_threads(threads)
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(2, mp_context=context, initializer=_load_worker_ensemble) as pool:

        def four_in_processes() -> None:
            list(pool.map(_predict_member, [observed] * 4, range(4)))

        report(
            "four members, whole map, 2 processes",
            median_ms(four_in_processes, repeats),
            "(1 thread each)",
        )


def bench_replan(
    world, config: ExplorationConfig, repeats: int, method_name: str, precision: str
) -> None:
    """One whole re-plan of `method_name` part-way through a run (t = 300): the learned
    ensemble on the known area plus sensor range (in process, two threads, as `python -m
    mapex run`), frontier clusters, cost map, reachability, scoring and the path to the goal."""
    import torch

    from mapex.prediction.learned import LearnedEnsemble

    explorer = explored_state(world, config, steps=300)
    explorer.method = make_method(method_name, config)
    threads = torch.get_num_threads()
    explorer.predictor = LearnedEnsemble(threads=2, precision=precision)
    suffix = "" if precision == "float32" else f", {precision}"
    report(
        f"re-plan with prediction ({method_name}{suffix})",
        median_ms(lambda: explorer.replan(300), repeats),
        f"({len(explorer.frontiers)} frontiers, t = 300)",
    )
    torch.set_num_threads(threads)


def bench_episode(world, config: ExplorationConfig, repeats: int, predictor_name: str) -> None:
    """A whole `nearest` episode as `python -m mapex run` runs it; the predictor only serves
    the IoU/TU metrics (G's whole-map prediction every 50 steps)."""
    predictor = make_predictor(predictor_name)
    times = []
    for _ in range(repeats):
        result = run_episode(world, "nearest", predictor, 0, 0, config)
        times.append(result.wall_time_s * 1e3)
    name = "nearest episode"  # the target line (metrics with the classical predictor)
    if predictor_name != "classical":
        name = f"nearest episode, {predictor_name}"
    report(
        name,
        statistics.median(times),
        f"({config.steps} steps incl. metrics with '{predictor_name}', median of {repeats}; "
        f"{statistics.median(times) / config.steps:.1f} ms/step)",
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mapex.bench", description=__doc__)
    parser.add_argument(
        "--world",
        default=str(DEFAULT_MAP),
        help="KTH map dir, generated:SEED or generated-open:SEED",
    )
    parser.add_argument("--repeats", type=int, default=50, help="repeats of the small benchmarks")
    parser.add_argument("--episodes", type=int, default=3, help="repeats of the episode benchmark")
    parser.add_argument("--steps", type=int, default=1000, help="episode length")
    args = parser.parse_args(argv)
    try:
        world = load_world(args.world)
    except WorldError as error:
        print(f"mapex.bench: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    config = ExplorationConfig(steps=args.steps)
    print(f"map {world.name}: {world.shape[0]} x {world.shape[1]} cells; medians in ms", flush=True)
    bench_scan(world, config, args.repeats)
    bench_scoring(world, config, args.repeats)
    bench_astar(world, config, max(args.repeats // 5, 3))
    bench_learned(world, max(args.repeats // 10, 3))
    for method_name in ("mapex", "mapex_plus"):
        for precision in PRECISIONS:
            bench_replan(world, config, max(args.repeats // 10, 3), method_name, precision)
    if args.episodes > 0:
        bench_episode(world, config, args.episodes, "classical")
        bench_episode(world, config, args.episodes, DEFAULT_PREDICTOR)
    return 0


if __name__ == "__main__":
    sys.exit(main())
