"""Sizing a cluster: episodes per hour against planners and predictor workers (issue 56).

    python -m deploy.throughput_model [--figure PNG] [--measure [--world W] [--steps T]]

A model on paper (docs/deploy.md, "Sizing a cluster"): an episode keeps one planner busy
for its steps and its blocking re-plan predictions, and asks every member for a known
amount of worker time; the cluster's throughput is the least of what the planners, the
busiest member's workers and (on one machine) the cores can sustain. Without `--measure`
it draws the figure from the figures measured on this project's machine (`MEASURED`);
`--measure` measures them again here (an in-process episode for the counts and the
planner's own time, one real worker answering recorded crops for the service times and
queue waits, `services.up` runs for the throughput points) and prints them.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mapex.exit_codes import EXIT_USAGE  # noqa: E402

SECONDS_PER_HOUR = 3600.0
FIGURE = Path(__file__).resolve().parents[1] / "docs" / "images" / "throughput_model.png"
PLANNER_LINES = (1, 2, 4, 8, 16, 32)  # planners drawn, one line each
MAX_WORKERS_PER_MEMBER = 32  # the figure's x range
MACHINE_CORES = 2  # this project's machine, where the points were measured


@dataclass(frozen=True)
class EpisodeDemand:
    """What one episode asks of the cluster; times in seconds (medians where measured)."""

    steps: int
    step_s: float  # planner and world CPU per step, predictions excluded
    replans: float  # re-plans: predictions the planner waits for
    replan_members: tuple[str, ...]  # the members each re-plan asks, at once
    replan_query_s: float  # one member's compute on a re-plan crop (worker compute_ms)
    metric_samples: float  # G's whole-map metric predictions: the planner does not wait
    metric_query_s: float  # one whole-map prediction of G
    round_trip_s: float  # a query's network and codec time beyond the compute

    def planner_s(self) -> float:
        """How long one episode holds its planner when no query waits in a queue."""
        return self.steps * self.step_s + self.replans * (self.replan_query_s + self.round_trip_s)

    def member_s(self) -> dict[str, float]:
        """Worker seconds one episode asks of each member."""
        busy = {member: self.replans * self.replan_query_s for member in self.replan_members}
        busy["g"] = busy.get("g", 0.0) + self.metric_samples * self.metric_query_s
        return busy

    def cpu_s(self) -> float:
        """CPU seconds of one episode, planner and workers together."""
        return self.steps * self.step_s + sum(self.member_s().values())


@dataclass(frozen=True)
class MeasuredPoint:
    """Episodes per hour measured with `planners` episodes at once and `workers` per member;
    `cores`: the CPU time all its processes got over its wall time (at most the machine's
    cores, fewer where other work shared them)."""

    planners: int
    workers: int
    episodes_per_hour: float
    cores: float


def bounds_per_hour(
    demand: EpisodeDemand, planners: int, workers: int, cores: float | None = None
) -> dict[str, float]:
    """Episodes per hour each resource allows: `planners` planners (one episode each at a
    time), `workers` workers per member (the busiest member decides), and, when everything
    shares one machine, its `cores`."""
    bounds = {
        "planners": planners / demand.planner_s(),
        "workers": workers / max(demand.member_s().values()),
    }
    if cores is not None:
        bounds["cores"] = cores / demand.cpu_s()
    return {name: SECONDS_PER_HOUR * rate for name, rate in bounds.items()}


def episodes_per_hour(
    demand: EpisodeDemand, planners: int, workers: int, cores: float | None = None
) -> float:
    """The model's throughput: the least of `bounds_per_hour`."""
    return min(bounds_per_hour(demand, planners, workers, cores).values())


# Measured on this project's machine (2 cores of an AMD EPYC, shared with other work: load
# average 14-16) on 2026-12-07 with `python -m deploy.throughput_model --measure` (KTH
# 50015847, 1000-step `mapex` episodes, float32, two views); medians. The service times
# are CPU times, which the other work hardly inflates (docs/deploy.md, Sizing a cluster).
MEASURED = EpisodeDemand(
    steps=1000,
    step_s=0.00256,
    replans=47,
    replan_members=("g1", "g2", "g3"),
    replan_query_s=0.135,
    metric_samples=21,
    metric_query_s=0.148,
    round_trip_s=0.0126,
)
MEASURED_POINTS = (
    MeasuredPoint(planners=1, workers=1, episodes_per_hour=109.4, cores=0.80),
    MeasuredPoint(planners=2, workers=1, episodes_per_hour=118.7, cores=1.07),
    MeasuredPoint(planners=2, workers=2, episodes_per_hour=115.3, cores=1.23),
)


def draw(demand: EpisodeDemand, points: Sequence[MeasuredPoint], path: Path) -> None:
    """The figure: episodes per hour against workers per member, one line per planner
    count (every process on a core of its own), and the measured points beside what the
    model predicts for each with the cores that run got."""
    workers = range(1, MAX_WORKERS_PER_MEMBER + 1)
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    colours = plt.get_cmap("viridis")
    for index, planners in enumerate(PLANNER_LINES):
        colour = colours(index / len(PLANNER_LINES))
        rates = [episodes_per_hour(demand, planners, w) for w in workers]
        ax.plot(workers, rates, color=colour, label=f"P = {planners} planners")
    one_machine = SECONDS_PER_HOUR * MACHINE_CORES / demand.cpu_s()
    ax.axhline(one_machine, color="grey", linestyle="--", linewidth=1,
               label=f"everything on one {MACHINE_CORES}-core machine")  # fmt: skip
    for index, point in enumerate(points):
        predicted = episodes_per_hour(demand, point.planners, point.workers, point.cores)
        ax.plot(point.workers, point.episodes_per_hour, "o", color="tab:red")
        ax.plot(point.workers, predicted, "x", color="tab:red")
        ax.annotate(f"P={point.planners}, W={point.workers}: {point.cores:.1f} cores",
                    (point.workers, point.episodes_per_hour), fontsize=7,
                    xytext=(8, -12 + 9 * index), textcoords="offset points")  # fmt: skip
    if points:
        ax.plot([], [], "o", color="tab:red", label=f"measured, {MACHINE_CORES}-core machine")
        ax.plot([], [], "x", color="tab:red", label="model, with the cores each run got")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ticks = [w for w in workers if w & (w - 1) == 0]  # powers of two
    ax.set_xticks(ticks, [str(w) for w in ticks])
    ax.set_xlabel("W: predictor workers per member (one core each)")
    ax.set_ylabel("episodes per hour")
    ax.set_title(
        f"{demand.steps}-step episodes: {demand.replans:.0f} re-plans x "
        f"{demand.replan_query_s * 1e3:.0f} ms, {demand.step_s * 1e3:.1f} ms planner per step",
        fontsize=9,
    )
    ax.grid(True, which="both", linewidth=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------- measuring


def measure(world: str, steps: int) -> tuple[EpisodeDemand, list[MeasuredPoint]]:
    """Measure the model's inputs and throughput points on this machine (minutes)."""
    demand, crops = _in_process(world, steps)
    demand = dataclasses.replace(demand, round_trip_s=_worker_service(crops))
    _distributed_step_s(world, steps)
    return demand, _throughput_points(world, steps)


def _in_process(world_spec: str, steps: int) -> tuple[EpisodeDemand, dict[str, list]]:
    """A `mapex` episode in one process, one torch thread as a worker has: the re-plans and
    metric samples it asks for, and the crops asked about (for the worker). Its times are
    CPU times of the one thread that does all the work, so other work on the machine does
    not inflate them: the planner's own per step, and one member's per query."""
    import torch

    from mapex.config import ExplorationConfig
    from mapex.episode import run_episode
    from mapex.prediction.learned import LearnedEnsemble
    from mapex.worlds import load_world

    class TimedEnsemble(LearnedEnsemble):
        def __init__(self) -> None:
            super().__init__()
            self.calls: list[tuple[tuple[int, ...], object, float]] = []

        def predict_members(self, observed, members):
            began = time.thread_time()
            answer = super().predict_members(observed, members)
            self.calls.append((tuple(members), observed.copy(), time.thread_time() - began))
            return answer

    torch.set_num_threads(1)
    ensemble = TimedEnsemble()
    world = load_world(world_spec)
    began = time.thread_time()
    result = run_episode(world, "mapex", ensemble, 0, 0, ExplorationConfig(steps=steps))
    episode_s = time.thread_time() - began
    metric = [(crop, s) for members, crop, s in ensemble.calls if members == (0,)]
    replan = [(crop, s / len(m)) for m, crop, s in ensemble.calls if m != (0,)]
    predicting_s = sum(s for _, _, s in ensemble.calls)
    demand = EpisodeDemand(
        steps=steps,
        step_s=(episode_s - predicting_s) / steps,
        replans=result.stats.replans,
        replan_members=("g1", "g2", "g3"),
        replan_query_s=statistics.median(s for _, s in replan),
        metric_samples=len(metric),
        metric_query_s=statistics.median(s for _, s in metric),
        round_trip_s=0.0,
    )
    _line("in process: re-plans per episode", demand.replans, "")
    _line("in process: metric samples per episode", demand.metric_samples, "")
    _line("in process: planner and world per step, CPU, no prediction", demand.step_s * 1e3, "ms")
    _line("in process: one member on a re-plan crop, CPU", demand.replan_query_s * 1e3, "ms")
    _line("in process: G on the whole map, CPU", demand.metric_query_s * 1e3, "ms")
    return demand, {"replan": [c for c, _ in replan], "metric": [c for c, _ in metric]}


SAMPLE_QUERIES = 12  # sequential queries per crop kind
BURST = 4  # queries sent at once to one worker
BURSTS = 4
WORKER = ("g1", "sizing")  # the member and worker id of the measured worker


def _worker_service(crops: dict[str, list]) -> float:
    """A real `services.predictor` worker on a loopback router answering recorded crops:
    its compute per query (the replies' compute_ms, wall time) and the queue waits of
    queries sent `BURST` at once are printed; the median round trip beyond the compute is
    returned."""
    from services.codec import DEFAULT_SERVICES
    from services.keys import alive_predictor_key, predict_key
    from services.messages import PredictReply, PredictRequest
    from services.supervisor import claim_hub, endpoint_silence
    from services.zenoh_config import open_session, zenoh_config

    port = 7490
    while not claim_hub(f"tcp/127.0.0.1:{port}"):
        port += 1
    endpoint = f"tcp/127.0.0.1:{port}"
    member, worker_id = WORKER
    commands = [
        ["deploy.router", "--listen", endpoint],
        ["services.predictor", "--member", member, "--worker-id", worker_id, "--mode",
         "client", "--connect", endpoint],
    ]  # fmt: skip
    processes = []
    try:
        for command in commands:
            processes.append(
                subprocess.Popen(
                    [sys.executable, "-m", *command],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
            while endpoint_silence(endpoint, DEFAULT_SERVICES.hub_probe_timeout_s) is not None:
                time.sleep(0.2)  # the router listens before the worker dials it
        session = open_session(zenoh_config("client", [endpoint]))
        try:
            token = alive_predictor_key(member, worker_id)
            while not any(r.ok is not None for r in session.liveliness().get(token)):
                time.sleep(0.2)
            budget_s = DEFAULT_SERVICES.predict_timeout_s
            ids = iter(range(10**9))

            def ask(batch: list) -> list[tuple[float, float]]:
                """(round trip, compute) of each crop of `batch`, all sent at once."""
                began = time.perf_counter()
                handlers = [
                    session.get(
                        predict_key(member, worker_id),
                        payload=PredictRequest(next(ids), crop, budget_s).encode(),
                        timeout=2 * budget_s * len(batch),
                    )
                    for crop in batch
                ]
                timed = []
                for handler in handlers:
                    answer = handler.recv()
                    if answer.ok is None:
                        said = answer.err.payload.to_bytes().decode(errors="replace")
                        raise RuntimeError(f"the worker gave no prediction: {said}")
                    reply = PredictReply.decode(answer.ok.payload.to_bytes())
                    timed.append((time.perf_counter() - began, reply.compute_ms / 1e3))
                return timed

            replans = crops["replan"]
            ask(replans[:1])  # the first query of a worker pays for its warm-up
            sequential = [ask([c])[0] for c in _spread(replans, SAMPLE_QUERIES)]
            metric = [ask([c])[0] for c in _spread(crops["metric"], SAMPLE_QUERIES)]
            round_trip_s = statistics.median(rtt - s for rtt, s in sequential)
            waits: dict[int, list[float]] = {}
            rest = _spread(replans[1::2], BURST * BURSTS)  # other crops: no cached answer
            for k in range(0, len(rest) - BURST + 1, BURST):
                timed = ask(rest[k : k + BURST])
                for position, (rtt, s) in enumerate(timed):
                    ahead = sum(c for _, c in timed[:position])
                    waits.setdefault(position, []).append((rtt - s - round_trip_s, ahead))
        finally:
            session.close()
    finally:
        for process in processes:
            process.kill()
            process.wait()
    replan_s = statistics.median(s for _, s in sequential)
    metric_s = statistics.median(s for _, s in metric)
    _line("worker: compute per re-plan query (compute_ms)", replan_s * 1e3, "ms")
    _line("worker: compute per whole-map G query", metric_s * 1e3, "ms")
    _line("worker: round trip beyond the compute", round_trip_s * 1e3, "ms")
    for position, pairs in sorted(waits.items()):
        wait = statistics.median(w for w, _ in pairs)
        ahead = statistics.median(a for _, a in pairs)
        _line(f"worker: queue wait with {position} queries ahead (their compute)",
              wait * 1e3, f"ms ({ahead * 1e3:.0f} ms)")  # fmt: skip
    return round_trip_s


def _distributed_step_s(world: str, steps: int) -> float:
    """The planner's wall time per step through `services.up` without waiting for a
    prediction: a `nearest` episode's loop (its G metric predictions go on meanwhile) over
    its steps (printed: a check on the in-process CPU time, which the model uses)."""
    import tempfile

    from services.bench import run_up

    with tempfile.TemporaryDirectory() as scratch:
        run = run_up(Path(scratch), world, "nearest", steps)
    step_s = run["runs"][0]["wall_time_s"] / steps
    _line("services.up: planner per step, nearest (no prediction waited for)", step_s * 1e3, "ms")
    return step_s


def _throughput_points(world: str, steps: int) -> list[MeasuredPoint]:
    """Episodes per hour of `services.up` runs here: episodes at once over the longest
    episode loop (start-up excluded, as a campaign's pool starts once), and the cores the
    run got: the CPU time of all its processes (they are waited for, so the children's
    resource usage holds them) over the whole command's wall time."""
    import resource
    import tempfile

    from services.bench import run_up

    def cpu_s() -> float:
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        return usage.ru_utime + usage.ru_stime

    points = []
    with tempfile.TemporaryDirectory() as scratch:
        for planners, workers in ((1, 1), (2, 1), (2, 2)):
            extra = ("--runs", str(planners), "--replicas", str(workers))
            began_cpu_s = cpu_s()
            run = run_up(Path(scratch) / f"p{planners}w{workers}", world, "mapex", steps, *extra)
            cores = (cpu_s() - began_cpu_s) / run["wall_s"]
            loop_s = max(record["wall_time_s"] for record in run["runs"])
            point = MeasuredPoint(planners, workers, SECONDS_PER_HOUR * planners / loop_s, cores)
            name = f"services.up, P={planners} W={workers}"
            _line(f"{name}: episodes per hour", point.episodes_per_hour, "")
            _line(f"{name}: cores it got (CPU / wall)", cores, "")
            points.append(point)
    return points


def _spread(items: list, count: int) -> list:
    """Up to `count` items spread evenly over `items`."""
    if len(items) <= count:
        return list(items)
    return [items[round(k * (len(items) - 1) / (count - 1))] for k in range(count)]


def _line(name: str, value: float, unit: str) -> None:
    print(f"{name:<62} {value:9.2f} {unit}", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m deploy.throughput_model", description=__doc__.split("\n\n")[2]
    )
    parser.add_argument("--figure", type=Path, default=FIGURE, help="PNG to write")
    parser.add_argument("--measure", action="store_true", help="measure the inputs here first")
    parser.add_argument("--world", default=None, help="with --measure (default: the bench's)")
    parser.add_argument("--steps", type=int, default=MEASURED.steps, help="with --measure")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error("--steps must be at least 1")
    if not args.figure.parent.is_dir():
        print(f"throughput_model: error: no folder {args.figure.parent}", file=sys.stderr)
        return EXIT_USAGE
    demand, points = MEASURED, list(MEASURED_POINTS)
    if args.measure:
        from mapex.bench import DEFAULT_MAP

        world = args.world or (str(DEFAULT_MAP) if DEFAULT_MAP.is_dir() else "default")
        demand, points = measure(world, args.steps)
        print(demand, points, sep="\n")
    draw(demand, points, args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
