"""A team's episode in one process: N robots, one shared observed map, one predictor.

The lockstep of docs/algorithms.md#teams: at each step t every robot sees its teammates'
claims as they stood after step t - 1 and chooses its motion (re-planning when its goal is
done or a teammate claimed it with a better score); the claims made at t are then settled
together; the world moves all robots (points: they may share a cell) and scans for each;
the scans are integrated into the shared map in robot order. So every robot holds the same
map at every t, and a team run is deterministic for a seed. A robot with nothing left to
explore stands still (a teammate's scan may give it a frontier again); the run ends when
no robot has anything left. The metrics are the single robot's, on the merged map (TU from
robot 0's start), plus each robot's path length and the overlap: the share of observed
cells that more than one robot observed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from mapex.config import ExplorationConfig
from mapex.episode import EpisodeResult, StepSource
from mapex.explorer import Explorer, ExplorerStats
from mapex.grid import UNKNOWN, Cell, new_observed_map
from mapex.prediction.base import Predictor
from mapex.recorder import MetricRecorder
from mapex.sensor import Scan, integrate_scan
from mapex.simulator import Simulator
from mapex.team.claims import ClaimBoard
from mapex.team.methods import TeamScorer, make_team_method
from mapex.team.starts import team_start_cells
from mapex.worlds import StartSpec, World

TeamStepListener = Callable[[int, list[Explorer], MetricRecorder], None]
"""Called after each step t (1..T) with every robot's explorer and the team's recorder."""


@dataclass
class TeamResult(EpisodeResult):
    """A team run's record: the `EpisodeResult` of the merged map (its `trajectory` and
    `stats` are robot 0's) plus every robot's trajectory, counters and path length."""

    trajectories: list[np.ndarray] = field(default_factory=list)  # int (n + 1, 2) per robot
    robot_stats: list[ExplorerStats] = field(default_factory=list)
    path_lengths_m: list[float] = field(default_factory=list)
    overlap: float = 0.0  # share of observed cells that more than one robot observed

    @property
    def robots(self) -> int:
        return len(self.trajectories)


class _Team:
    """The robots' explorers around one shared map, and what each has seen on its own."""

    def __init__(
        self,
        world: World,
        method_name: str,
        predictor: Predictor | None,
        robots: int,
        seed: int,
        config: ExplorationConfig,
    ) -> None:
        self.config = config
        self.observed = new_observed_map(world.shape)
        self.explorers = []
        for robot in range(robots):
            explorer = Explorer(
                world.shape, make_team_method(method_name, config), predictor, config, seed + robot
            )
            explorer.observed = self.observed  # one map for the whole team
            self.explorers.append(explorer)
        self.seen = [new_observed_map(world.shape) for _ in range(robots)]  # for the overlap
        self.board = ClaimBoard(world.shape, config.team.claim_conflict_cells)

    def observe(self, scans: Sequence[Scan]) -> None:
        """Integrate every robot's scan, in robot order, into the shared map."""
        for explorer, seen, scan in zip(self.explorers, self.seen, scans, strict=True):
            explorer.observe(scan)
            integrate_scan(seen, scan, self.config.sensor)

    def motions(self, t: int, done: list[bool]) -> list[np.ndarray | None]:
        """Each robot's motion for step t (None: nothing left for it now), then the claims
        made at t settled (module doc)."""
        motions, made = [], {}
        for robot, explorer in enumerate(self.explorers):
            method: TeamScorer = explorer.method  # type: ignore[assignment]
            method.teammates = self.board.teammates_of(robot)
            replans = explorer.stats.replans
            motion = explorer.next_motion(t)
            if explorer.stats.replans != replans and method.claims:
                made[robot] = method.claim_of(robot, t)
            done[robot] = motion is None
            motions.append(motion)
        for robot in self.board.settle(made):
            self.explorers[robot].goal = self.explorers[robot].path = None
        return motions

    def overlap(self) -> float:
        known = np.stack([seen != UNKNOWN for seen in self.seen])
        counts = known.sum(axis=0)
        return float((counts > 1).sum() / max((counts > 0).sum(), 1))


def run_team_episode(
    world: World,
    method_name: str,
    predictor: Predictor | None,
    robots: int,
    starts: Sequence[StartSpec] = (0,),
    seed: int = 0,
    config: ExplorationConfig | None = None,
    on_step: TeamStepListener | None = None,
    source: StepSource | None = None,
) -> TeamResult:
    """Explore `world` with `robots` robots of team method `method_name` (module doc).

    `starts`: one start the team deploys around (`team.spacing_cells` apart) or one per
    robot. `source` (default: an in-process `Simulator`) moves and scans robots 0..N-1.
    """
    config = config or ExplorationConfig()
    world.check_size(config.world.max_cells)
    cells = team_start_cells(world, list(starts), robots, config)
    began = time.perf_counter()
    if source is None:
        source = Simulator(world, cells, config.sensor, config.motion)
    team = _Team(world, method_name, predictor, robots, seed, config)
    recorder = MetricRecorder(world, cells[0], predictor, config.metrics)
    team.observe([source.scan(robot) for robot in range(robots)])
    trajectories = [[explorer.pose.copy()] for explorer in team.explorers]
    finished_at, done = None, [False] * robots
    for t in range(config.steps + 1):
        if recorder.is_sample_step(t):
            recorder.record(t, team.observed)
        if t == config.steps:
            break
        motions = team.motions(t, done)
        if all(done):
            finished_at = t
            recorder.hold_to_end(t, config.steps, team.observed)
            break
        empty = np.zeros((0, 2), dtype=np.int64)
        scans = [
            source.step(robot, empty if motion is None else motion)
            for robot, motion in enumerate(motions)
        ]
        team.observe(scans)
        for trajectory, explorer in zip(trajectories, team.explorers, strict=True):
            trajectory.append(explorer.pose.copy())
        if on_step is not None:
            on_step(t + 1, team.explorers, recorder)
    recorder.flush()
    return _result(world, method_name, predictor, cells, starts, seed, config, team, recorder,
                   trajectories, finished_at, time.perf_counter() - began)  # fmt: skip


def _result(
    world: World,
    method_name: str,
    predictor: Predictor | None,
    cells: list[Cell],
    starts: Sequence[StartSpec],
    seed: int,
    config: ExplorationConfig,
    team: _Team,
    recorder: MetricRecorder,
    trajectories: list[list[np.ndarray]],
    finished_at: int | None,
    wall_time_s: float,
) -> TeamResult:
    paths = [np.asarray(path, dtype=np.int64) for path in trajectories]
    lengths = [
        float(np.hypot(*np.diff(path, axis=0).T).sum()) * world.resolution_m for path in paths
    ]
    first = team.explorers[0]
    start = starts[0] if len(starts) == 1 else None
    return TeamResult(
        world=world.name,
        method=method_name,
        predictor=None if predictor is None else predictor.name,
        start_index=start if isinstance(start, int) else None,
        start=cells[0],
        seed=seed,
        steps=config.steps,
        curves=recorder.curves,
        trajectory=paths[0],
        finished_at=finished_at,
        end_reason="budget" if finished_at is None else (first.end_reason or "explored"),
        stats=first.stats,
        final_observed=team.observed.copy(),
        final_prediction=recorder.last_prediction,
        wall_time_s=wall_time_s,
        config=config,
        degraded_samples=recorder.degraded_samples,
        metric_workers=recorder.member_workers,
        snapshots=recorder.snapshots,
        trajectories=paths,
        robot_stats=[explorer.stats for explorer in team.explorers],
        path_lengths_m=lengths,
        overlap=team.overlap(),
    )
