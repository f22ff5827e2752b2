"""`python -m services.bench`: what the distribution costs and what the pool buys (figures).

On one map (default: KTH 50015847, the largest development map), per part of `--parts`:
the per-step overhead of a distributed episode (overhead); the wall time and memory of a
1000-step `mapex` run through `services.up` (mapex); two runs sharing the pool (pool);
what a hung worker costs (hung); a team of 4 robots against one (team). Each figure is a
median over `--repeat` runs. Benchmarks print figures; they never fail. What each part
measures, and the figures: docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from mapex.bench import DEFAULT_MAP
from mapex.config import ExplorationConfig
from mapex.episode import run_episode
from mapex.prediction.learned import LearnedEnsemble
from mapex.worlds import load_world, world_spec_help
from services.codec import DEFAULT_SERVICES
from services.supervisor import claim_hub

MEMORY_POLL_S = 0.5
PAGE_KIB = 4
TARGETS = {"overhead_pct": 20.0, "mapex_wall_s": 30.0, "memory_gib": 4.0}
OLD_PATH_FLAGS = ("--inference", "plain", "--views", "2")  # the workers before issue #50


def tree_rss_kib(root_pid: int) -> int:
    """Total resident memory of `root_pid` and all its descendants, in KiB (from /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue
        pid = int(stat.parent.name)
        children.setdefault(int(fields[1]), []).append(pid)
        rss[pid] = int(fields[21]) * PAGE_KIB
    total, stack = 0, [root_pid]
    while stack:
        pid = stack.pop()
        total += rss.get(pid, 0)
        stack.extend(children.get(pid, []))
    return total


def run_up(
    out_dir: Path,
    world: str,
    method: str,
    steps: int,
    *extra: str,
    by_hand: str | None = None,
    hang_after: int | None = None,
) -> dict:
    """One `services.up` run: wall time, peak memory, its log and the metrics.json of each
    run. `by_hand`: also start a worker of that member on the same hub, by hand (tell
    services.up `--members` without it), hanging after `hang_after` predictions if given."""
    port = 7480
    while not claim_hub(f"tcp/127.0.0.1:{port}"):
        port += 1
    command = [
        sys.executable, "-m", "services.up", "--world", world, "--method", method,
        "--steps", str(steps), "--out", str(out_dir), "--no-progress",
        "--listen", f"tcp/127.0.0.1:{port}", "--run-prefix", "bench", *extra,
    ]  # fmt: skip
    began = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    log = open(out_dir / "up.log", "wb")  # noqa: SIM115 (closed below, after the run)
    process = subprocess.Popen(command, stdout=log, stderr=log)
    peak = [0]

    def sample() -> None:
        while process.poll() is None:
            peak[0] = max(peak[0], tree_rss_kib(process.pid))
            time.sleep(MEMORY_POLL_S)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    extra_worker = None
    if by_hand is not None:
        hang = () if hang_after is None else ("--hang-after", str(hang_after))
        extra_worker = subprocess.Popen(
            [sys.executable, "-m", "services.predictor", "--member", by_hand, "--worker-id",
             "by-hand", *hang, "--connect", f"tcp/127.0.0.1:{port}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
    code = process.wait()
    log.close()
    if extra_worker is not None:
        extra_worker.kill()
        extra_worker.wait()
    wall_s = time.perf_counter() - began
    sampler.join()
    if code != 0:
        raise RuntimeError(f"services.up exited with {code}: {' '.join(command)}")
    runs = [json.loads(p.read_text()) for p in sorted(out_dir.glob("*/metrics.json"))]
    log_text = (out_dir / "up.log").read_text(errors="replace")
    return {"wall_s": wall_s, "peak_gib": peak[0] / 2**20, "runs": runs, "log": log_text}


def in_process_loop_s(world_spec: str, method: str, steps: int) -> float:
    """Episode-loop wall time of the same episode in one process (one torch thread)."""
    torch.set_num_threads(1)
    predictor = LearnedEnsemble()
    config = ExplorationConfig(steps=steps)
    result = run_episode(load_world(world_spec), method, predictor, 0, 0, config)
    return result.wall_time_s


def line(name: str, value: float, unit: str, target: float | None = None) -> None:
    bound = f"  (target <= {target:g} {unit})" if target is not None else ""
    print(f"{name:<58} {value:9.2f} {unit}{bound}", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.bench", description=__doc__)
    parser.add_argument(
        "--world",
        default=str(DEFAULT_MAP) if DEFAULT_MAP.is_dir() else "default",
        help=f"the world: {world_spec_help()}; default: %(default)s",
    )
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure (median)")
    parser.add_argument("--pool-repeat", type=int, default=1, help="runs per pool figure")
    parser.add_argument(
        "--parts",
        default="overhead,mapex,pool,hung,team",
        help="comma-separated subset of overhead,mapex,pool,hung,team (default: all)",
    )
    parser.add_argument("--hung-steps", type=int, default=300, help="steps of the hung runs")
    parser.add_argument("--team-steps", type=int, default=300, help="steps of the team runs")
    parser.add_argument("--team-robots", type=int, default=4, help="robots of the team run")
    parser.add_argument(
        "--team-methods",
        default="mapex_team",
        help="comma-separated team methods, each benched against one robot (default: %(default)s)",
    )
    args = parser.parse_args(argv)
    print(f"world {args.world}, {args.steps} steps, median of {args.repeat}", flush=True)
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(scratch)

        def ups(
            name: str, method: str, *extra: str, repeat: int = args.repeat, **options
        ) -> list[dict]:
            steps = options.pop("steps", args.steps)
            return [
                run_up(root / f"{name}{i}", args.world, method, steps, *extra, **options)
                for i in range(repeat)
            ]

        parts = set(args.parts.split(","))
        if "overhead" in parts:
            bench_overhead(args, ups)
        if "mapex" in parts:
            bench_mapex(ups)
        if "pool" in parts:
            bench_pool(args, ups)
        if "hung" in parts:
            bench_hung_worker(args, ups)
        if "team" in parts:
            bench_team(args, ups)
    return 0


def bench_overhead(args: argparse.Namespace, ups) -> None:
    """Item 1: the `nearest` episode loop distributed versus in one process."""
    local = statistics.median(
        in_process_loop_s(args.world, "nearest", args.steps) for _ in range(args.repeat)
    )
    remote = statistics.median(run["runs"][0]["wall_time_s"] for run in ups("nearest", "nearest"))
    line("nearest episode loop, in one process", local, "s")
    line("nearest episode loop, distributed", remote, "s")
    overhead_pct = (remote / local - 1) * 100
    line("per-step overhead of the distribution", overhead_pct, "%", TARGETS["overhead_pct"])


def bench_mapex(ups) -> None:
    """Item 2: a whole `mapex` run through services.up: wall time and peak memory, with the
    workers on the inference path before issue #50 (plain module, two views) and now."""
    old = ups("mapex-old", "mapex", *OLD_PATH_FLAGS)
    line("mapex episode via services.up, whole command [old path]", _median(old, "wall_s"), "s")
    mapex = ups("mapex", "mapex")
    wall_s, peak_gib = _median(mapex, "wall_s"), _median(mapex, "peak_gib")
    line("mapex episode via services.up, whole command", wall_s, "s", TARGETS["mapex_wall_s"])
    line("peak memory of all processes (mapex run)", peak_gib, "GiB", TARGETS["memory_gib"])
    loop = lambda runs: statistics.median(run["runs"][0]["wall_time_s"] for run in runs)  # noqa: E731
    line("  its episode loop [old path]", loop(old), "s")
    line("  its episode loop", loop(mapex), "s")


def bench_pool(args: argparse.Namespace, ups) -> None:
    """Item 3: two runs at once sharing the pool, one or two workers per member."""
    for replicas in (1, 2):
        extra = ("--runs", "2", "--replicas", str(replicas))
        shared = ups(f"pool{replicas}-", "mapex", *extra, repeat=args.pool_repeat)
        name = f"two mapex runs at once, {replicas} worker(s) per member (median of {len(shared)})"
        line(name, _median(shared, "wall_s"), "s")


def bench_hung_worker(args: argparse.Namespace, ups) -> None:
    """Item 4: a run whose g1 worker hangs after three predictions against one where it
    does not (the same processes otherwise)."""
    steps, others = args.hung_steps, ("--members", "g,g2,g3")
    healthy = ups("healthy", "mapex", *others, steps=steps, by_hand="g1")
    hung = ups("hung", "mapex", *others, steps=steps, by_hand="g1", hang_after=3)
    loop = lambda runs: statistics.median(run["runs"][0]["wall_time_s"] for run in runs)  # noqa: E731
    timeouts = statistics.median(run["log"].count("gave no prediction: Timeout") for run in hung)
    degraded = statistics.median(len(run["runs"][0]["degraded_steps"]) for run in hung)
    timeout_s = DEFAULT_SERVICES.predict_timeout_s
    line(f"mapex episode loop, {steps} steps, g1 worker healthy", loop(healthy), "s")
    line(f"mapex episode loop, {steps} steps, g1 worker hung", loop(hung), "s")
    line("extra loop time with the hung worker", loop(hung) - loop(healthy), "s", timeout_s)
    line("queries that waited out the timeout (hung run)", timeouts, "", 1)
    line("re-plans without g1 (degraded) in the hung run", degraded, "")
    line("  if each of those had waited the timeout (no benching)", degraded * timeout_s, "s")


def bench_team(args: argparse.Namespace, ups) -> None:
    """Item 5: per-step wall time of a team run (each of `--team-methods`) against a single
    robot's."""
    steps, robots = args.team_steps, args.team_robots
    per_step = lambda runs: statistics.median(  # noqa: E731
        max(record["wall_time_s"] for record in run["runs"]) / steps for run in runs
    )
    coverage = lambda runs: statistics.median(run["runs"][0]["auc"]["coverage"] for run in runs)  # noqa: E731
    single = ups("single", "mapex", steps=steps)
    line(f"single-robot mapex, wall time per step ({steps} steps)", per_step(single) * 1e3, "ms")
    line("coverage AUC, single robot", coverage(single), "")
    for method in args.team_methods.split(","):
        team = ups(method, method, "--robots", str(robots), steps=steps)
        line(f"{robots}-robot {method}, wall time per team step", per_step(team) * 1e3, "ms")
        line(f"ratio {method} / single", per_step(team) / per_step(single), "x", 2.0)
        line(f"coverage AUC, {method} team of {robots}", coverage(team), "")


def _median(runs: list[dict], key: str) -> float:
    return statistics.median(run[key] for run in runs)


if __name__ == "__main__":
    sys.exit(main())
