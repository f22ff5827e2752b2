"""One exploration episode: a team of N >= 1 robots, one shared map, one predictor.

Every run, a single robot's included, is this lockstep (docs/algorithms.md#teams): at each
step the robots decide their motions, the world moves them all and scans for each, and the
scans are integrated into the shared map in robot order. Deterministic for a world,
starts, method, predictor and seed. The world is simulated here (`SimulatedWorld`) or is
a world process (`services.world_client`), and a planner process decides only its robot.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from mapex.config import ExplorationConfig
from mapex.explorer import Explorer, ExplorerStats
from mapex.grid import Cell
from mapex.methods import records_team
from mapex.methods.claims import Claim
from mapex.prediction.base import Predictor
from mapex.recorder import COVERAGE_REACHED as COVERAGE_REACHED  # the ends a run may have
from mapex.recorder import IOU_REACHED as IOU_REACHED
from mapex.recorder import MetricCurves, MetricRecorder
from mapex.sensor import Scan
from mapex.simulator import Simulator
from mapex.team.starts import team_start_cells
from mapex.team.team import Decision, Team
from mapex.worlds import StartSpec, World, normalise_start

StepListener = Callable[[int, list[Explorer], MetricRecorder], None]
"""Called after each step t (1..T) with the explorers decided here and the recorder."""


@dataclass(frozen=True)
class WorldStep:
    """What the world answers for one step: every robot's scan after it, the claims made at
    it (robot -> claim, None: withdrawn) and whether the team is finished (no step taken)."""

    scans: list[Scan]
    claims: dict[int, Claim | None]
    finished: bool = False
    lost: tuple[int, ...] = ()  # robots whose planner is gone (a world process says so)


class StepSource(Protocol):
    """Who moves the robots and scans: `SimulatedWorld` here, or a world process."""

    def initial(self) -> list[Scan]: ...

    def step(self, t: int, decisions: list[Decision]) -> WorldStep: ...


class SimulatedWorld:
    """The world simulated in this process; every robot decides here."""

    def __init__(self, simulator: Simulator, robots: int) -> None:
        self.simulator = simulator
        self.robots = robots

    def initial(self) -> list[Scan]:
        return [self.simulator.scan(robot) for robot in range(self.robots)]

    def step(self, t: int, decisions: list[Decision]) -> WorldStep:
        claims = {d.robot: d.claim for d in decisions if d.claimed}
        if all(d.motion is None for d in decisions):
            return WorldStep([], claims, finished=True)
        empty = np.zeros((0, 2), dtype=np.int64)
        scans = [
            self.simulator.step(d.robot, empty if d.motion is None else d.motion) for d in decisions
        ]
        return WorldStep(scans, claims)


@dataclass
class EpisodeResult:
    """Everything a run produces: curves, trajectories, final maps and counters. `trajectory`
    and `stats` are robot 0's (or the first robot decided here)."""

    world: str
    method: str
    predictor: str | None
    start_index: int | None  # the corner 0-3, None for an explicit start cell
    start: Cell
    seed: int
    steps: int
    curves: MetricCurves
    trajectory: np.ndarray  # int (n + 1, 2): pose after the initial scan, then after each step
    finished_at: int | None  # step at which the robot gave up (early termination)
    # "budget" (T reached), "explored" (no frontier left), "unreachable", IOU_REACHED or
    # COVERAGE_REACHED
    end_reason: str
    stats: ExplorerStats
    final_observed: np.ndarray
    final_prediction: np.ndarray | None  # G's whole-map prediction at the end
    wall_time_s: float = 0.0
    config: ExplorationConfig = field(default_factory=ExplorationConfig)
    degraded_samples: list[int] = field(default_factory=list)  # metric samples without G
    degraded_from_start: str | None = None  # why the run was expected to degrade (size)
    # (t, who answered G) of each metric sample's prediction served by remote workers
    metric_workers: list[tuple[int, dict[str, str]]] = field(default_factory=list)
    snapshots: dict[int, tuple[np.ndarray, np.ndarray | None]] = field(default_factory=dict)
    trajectories: list[np.ndarray] = field(default_factory=list)  # int (n + 1, 2) per robot
    robot_stats: list[ExplorerStats] = field(default_factory=list)  # of the robots run here
    path_lengths_m: list[float] = field(default_factory=list)
    overlap: float = 0.0  # share of observed cells that more than one robot observed
    lost_at: dict[int, int] = field(default_factory=dict)  # robot -> step it was found lost

    @property
    def robots(self) -> int:
        return max(len(self.trajectories), 1)

    @property
    def is_team(self) -> bool:
        """Whether the record carries the team's size and fields (`records_team`)."""
        return records_team(self.method, self.robots)

    @property
    def start_spec(self) -> StartSpec:
        """The start as it was asked for: the corner index, or the explicit cell."""
        return self.start if self.start_index is None else self.start_index


def run_episode(
    world: World,
    method_name: str,
    predictor: Predictor | None,
    starts: StartSpec | list[StartSpec] = 0,
    seed: int = 0,
    config: ExplorationConfig | None = None,
    on_step: StepListener | None = None,
    source: StepSource | None = None,
    robots: int = 1,
    local: Sequence[int] | None = None,
) -> EpisodeResult:
    """Explore `world` with `robots` robots of `method_name` for `config.steps` steps.

    `starts`: a corner 0-3 or a cell (the team deploys around it, `team.spacing_cells`
    apart) or a list of one start per robot. `source` (default: `SimulatedWorld`) moves
    and scans the robots; a world process must have placed them at the same cells.
    `local`: the robots decided here (default: all; a planner process runs only its own).
    A start the world cannot take raises WorldError.
    """
    config = config or ExplorationConfig()
    world.check_size(config.world.max_cells)
    asked = [normalise_start(s) for s in (starts if isinstance(starts, list) else [starts])]
    cells = team_start_cells(world, asked, robots, config)
    began = time.perf_counter()
    if source is None:
        source = SimulatedWorld(Simulator(world, cells, config.sensor, config.motion), robots)
    local = list(range(robots)) if local is None else list(local)
    team = Team(world.shape, method_name, predictor, robots, seed, config, local)
    recorder = MetricRecorder(world, cells[0], predictor, config.metrics)
    team.observe(source.initial())
    finished_at, end_reason = None, "budget"
    for t in range(config.steps + 1):
        if (reason := recorder.at_step(t, team.observed, config.until_iou)) and t < config.steps:
            finished_at, end_reason = t, reason
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
    start = asked[0] if len(asked) == 1 else None
    return _result(world, method_name, predictor, cells, start, seed, config, team, recorder,
                   finished_at, end_reason, time.perf_counter() - began)  # fmt: skip


def _result(
    world: World,
    method_name: str,
    predictor: Predictor | None,
    cells: list[Cell],
    start: StartSpec | None,
    seed: int,
    config: ExplorationConfig,
    team: Team,
    recorder: MetricRecorder,
    finished_at: int | None,
    end_reason: str,
    wall_time_s: float,
) -> EpisodeResult:
    paths = [np.asarray(path, dtype=np.int64) for path in team.trajectories]
    lengths = [
        float(np.hypot(*np.diff(path, axis=0).T).sum()) * world.resolution_m for path in paths
    ]
    first = next(iter(team.explorers.values()))
    return EpisodeResult(
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
