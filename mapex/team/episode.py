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
from typing import Protocol

import numpy as np

from mapex.config import ExplorationConfig
from mapex.episode import IOU_REACHED, EpisodeResult
from mapex.explorer import Explorer, ExplorerStats
from mapex.grid import Cell, new_observed_map
from mapex.prediction.base import Predictor
from mapex.recorder import MetricRecorder
from mapex.sensor import Scan, integrate_scan
from mapex.simulator import Simulator
from mapex.team.claims import Claim, ClaimBoard
from mapex.team.methods import TeamScorer, make_team_method
from mapex.team.shared_prediction import EpochPrediction, TeammateExplorer
from mapex.team.starts import team_start_cells
from mapex.worlds import StartSpec, World

TeamStepListener = Callable[[int, list[Explorer], MetricRecorder], None]
"""Called after each step t (1..T) with the explorers run here and the team's recorder."""


@dataclass(frozen=True)
class Decision:
    """What robot `robot` does at one step: its motion (None: nothing left for it now) and,
    when it re-planned with a claiming method (`claimed`), its new claim (None: no goal)."""

    robot: int
    motion: np.ndarray | None
    claimed: bool = False
    claim: Claim | None = None


@dataclass(frozen=True)
class TeamStep:
    """What the world answers for one step: every robot's scan after it, the claims made at
    it (robot -> claim, None: withdrawn) and whether the team is finished (no step taken)."""

    scans: list[Scan]
    claims: dict[int, Claim | None]
    finished: bool = False
    lost: tuple[int, ...] = ()  # robots whose planner is gone (a world process says so)


class TeamStepSource(Protocol):
    """Who moves the team and scans: `SimulatedTeam` here, or a world process."""

    def initial(self) -> list[Scan]: ...

    def step(self, t: int, decisions: list[Decision]) -> TeamStep: ...


class SimulatedTeam:
    """The team's world simulated in this process; every robot decides here."""

    def __init__(self, simulator: Simulator, robots: int) -> None:
        self.simulator = simulator
        self.robots = robots

    def initial(self) -> list[Scan]:
        return [self.simulator.scan(robot) for robot in range(self.robots)]

    def step(self, t: int, decisions: list[Decision]) -> TeamStep:
        claims = {d.robot: d.claim for d in decisions if d.claimed}
        if all(d.motion is None for d in decisions):
            return TeamStep([], claims, finished=True)
        empty = np.zeros((0, 2), dtype=np.int64)
        scans = [
            self.simulator.step(d.robot, empty if d.motion is None else d.motion) for d in decisions
        ]
        return TeamStep(scans, claims)


@dataclass
class TeamResult(EpisodeResult):
    """A team run's record: the `EpisodeResult` of the merged map (its `trajectory` and
    `stats` are robot 0's, or the first robot run here) plus every robot's trajectory,
    counters (of the robots run here) and path length."""

    trajectories: list[np.ndarray] = field(default_factory=list)  # int (n + 1, 2) per robot
    robot_stats: list[ExplorerStats] = field(default_factory=list)
    path_lengths_m: list[float] = field(default_factory=list)
    overlap: float = 0.0  # share of observed cells that more than one robot observed
    lost_at: dict[int, int] = field(default_factory=dict)  # robot -> step it was found lost

    @property
    def robots(self) -> int:
        return len(self.trajectories)


class Team:
    """One shared map, the claim board, and the explorers of the robots decided here (all
    of them in one process; one in a robot's planner process), plus what each robot has
    seen on its own and where each has been."""

    def __init__(
        self,
        shape: tuple[int, int],
        method_name: str,
        predictor: Predictor | None,
        robots: int,
        seed: int,
        config: ExplorationConfig,
        local: Sequence[int],
    ) -> None:
        self.config = config
        self.robots = robots
        self.observed = new_observed_map(shape)
        self.explorers: dict[int, Explorer] = {}
        # a team of one predicts at every re-plan, exactly as a single robot
        epoch_steps = config.team.prediction_epoch_steps if robots > 1 else 1
        self.shared = None if predictor is None else EpochPrediction(
            predictor, epoch_steps, config.sensor.range_cells
        )  # fmt: skip
        for robot in local:
            method = make_team_method(method_name, config)
            explorer = TeammateExplorer(shape, method, self.shared, config, seed + robot)
            explorer.observed = self.observed  # one map for the whole team
            self.explorers[robot] = explorer
        # the cells each robot's own scans walked, for the overlap
        self.seen = [np.zeros(shape, dtype=bool) for _ in range(robots)]
        self.trajectories: list[list[np.ndarray]] = [[] for _ in range(robots)]
        self.board = ClaimBoard(shape, config.team.claim_conflict_cells)
        self.lost_at: dict[int, int] = {}

    def mark_lost(self, robots: Sequence[int], t: int) -> None:
        """Note the step at which each robot of `robots` was first reported lost."""
        for robot in robots:
            self.lost_at.setdefault(robot, t)

    def decide(self, t: int) -> list[Decision]:
        """The decisions of the robots run here for step t, each seeing the claims as they
        stood after step t - 1."""
        if self.shared is not None:
            self.shared.begin_step(t, self.observed)
        decisions = []
        for robot, explorer in self.explorers.items():
            method: TeamScorer = explorer.method  # type: ignore[assignment]
            method.teammates = self.board.teammates_of(robot)
            replans = explorer.stats.replans
            motion = explorer.next_motion(t)
            claimed = explorer.stats.replans != replans and method.claims
            claim = method.claim_of(robot, t) if claimed else None
            decisions.append(Decision(robot, motion, claimed, claim))
        return decisions

    def settle(self, claims: dict[int, Claim | None]) -> None:
        """Settle the claims made at one step; robots run here that lost theirs re-plan."""
        for robot in self.board.settle(claims):
            if robot in self.explorers:
                self.explorers[robot].goal = self.explorers[robot].path = None

    def observe(self, scans: Sequence[Scan]) -> None:
        """Integrate every robot's scan, in robot order, into the shared map."""
        for robot, scan in enumerate(scans):
            if robot in self.explorers:
                self.explorers[robot].observe(scan, self.seen[robot])
            else:
                integrate_scan(self.observed, scan, self.config.sensor, self.seen[robot])
            self.trajectories[robot].append(np.asarray(scan.pose, dtype=np.int64))

    def overlap(self) -> float:
        counts = np.sum(self.seen, axis=0, dtype=np.int32)
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
    source: TeamStepSource | None = None,
    local: Sequence[int] | None = None,
) -> TeamResult:
    """Explore `world` with `robots` robots of team method `method_name` (module doc).

    `starts`: one start the team deploys around (`team.spacing_cells` apart) or one per
    robot. `source` (default: `SimulatedTeam`) moves and scans the team; `local`: the robots
    decided here (default: all; a robot's planner process runs only its own).
    """
    config = config or ExplorationConfig()
    world.check_size(config.world.max_cells)
    cells = team_start_cells(world, list(starts), robots, config)
    began = time.perf_counter()
    if source is None:
        source = SimulatedTeam(Simulator(world, cells, config.sensor, config.motion), robots)
    local = list(range(robots)) if local is None else list(local)
    team = Team(world.shape, method_name, predictor, robots, seed, config, local)
    recorder = MetricRecorder(world, cells[0], predictor, config.metrics)
    team.observe(source.initial())
    finished_at, end_reason = None, "budget"
    for t in range(config.steps + 1):
        if recorder.at_step(t, team.observed, config.until_iou) and t < config.steps:
            finished_at, end_reason = t, IOU_REACHED
            recorder.hold_to_end(t, config.steps, team.observed)
            break
        if t == config.steps:
            break
        step = source.step(t, team.decide(t))
        team.settle(step.claims)
        team.mark_lost(step.lost, t)
        if step.finished:
            finished_at = t
            end_reason = next(iter(team.explorers.values())).end_reason or "explored"
            recorder.hold_to_end(t, config.steps, team.observed)
            break
        team.observe(step.scans)
        if on_step is not None:
            on_step(t + 1, list(team.explorers.values()), recorder)
    recorder.flush()
    return _result(world, method_name, predictor, cells, starts, seed, config, team, recorder,
                   finished_at, end_reason, time.perf_counter() - began)  # fmt: skip


def _result(
    world: World,
    method_name: str,
    predictor: Predictor | None,
    cells: list[Cell],
    starts: Sequence[StartSpec],
    seed: int,
    config: ExplorationConfig,
    team: Team,
    recorder: MetricRecorder,
    finished_at: int | None,
    end_reason: str,
    wall_time_s: float,
) -> TeamResult:
    paths = [np.asarray(path, dtype=np.int64) for path in team.trajectories]
    lengths = [
        float(np.hypot(*np.diff(path, axis=0).T).sum()) * world.resolution_m for path in paths
    ]
    first = next(iter(team.explorers.values()))
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
        end_reason=end_reason,
        stats=first.stats,
        final_observed=team.observed.copy(),
        final_prediction=recorder.last_prediction,
        wall_time_s=wall_time_s,
        config=config,
        degraded_samples=recorder.degraded_samples,
        metric_workers=recorder.member_workers,
        snapshots=recorder.snapshots,
        trajectories=paths,
        robot_stats=[explorer.stats for explorer in team.explorers.values()],
        path_lengths_m=lengths,
        overlap=team.overlap(),
        lost_at=dict(team.lost_at),
    )
