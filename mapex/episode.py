"""One exploration episode in one process: world + method + predictor + seed -> record.

The loop is the same lockstep the distributed services run: the simulator
answers each step with a scan, the explorer integrates it and chooses the next
motion. Deterministic for a given world, start, method, predictor and seed.
`services.planner` runs this very loop with a `StepSource` that asks the world
process over Zenoh and a predictor whose members are worker processes.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from mapex.config import ExplorationConfig
from mapex.explorer import Explorer, ExplorerStats
from mapex.grid import Cell
from mapex.methods import make_method
from mapex.prediction.base import Predictor
from mapex.recorder import MetricCurves, MetricRecorder
from mapex.sensor import Scan
from mapex.simulator import Simulator
from mapex.worlds import StartSpec, World, normalise_start, start_cell


class StepSource(Protocol):
    """Who moves the robot and scans: the in-process `Simulator` or a world process."""

    def scan(self, robot: int) -> Scan: ...

    def step(self, robot: int, cells: np.ndarray) -> Scan: ...


IOU_REACHED = "iou_reached"  # the run ended because G's IoU reached `config.until_iou`

StepListener = Callable[[int, Explorer, MetricRecorder], None]
"""Called after each step t (1..T) with the explorer and recorder (progress bars, publishing)."""


@dataclass
class EpisodeResult:
    """Everything a run produces: curves, trajectory, final maps and counters."""

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
    # "budget" (T reached), "explored" (no frontier left), "unreachable" or IOU_REACHED
    end_reason: str
    stats: ExplorerStats
    final_observed: np.ndarray
    final_prediction: np.ndarray | None  # G's whole-map prediction at the end
    wall_time_s: float = 0.0
    config: ExplorationConfig = field(default_factory=ExplorationConfig)
    degraded_samples: list[int] = field(default_factory=list)  # metric samples without G
    degraded_from_start: str | None = None  # why the run was expected to degrade (size)
    metric_workers: list[tuple[int, dict[str, str]]] = field(default_factory=list)  # (t, who
    # answered G) of each metric sample's prediction served by remote workers
    snapshots: dict[int, tuple[np.ndarray, np.ndarray | None]] = field(default_factory=dict)

    @property
    def start_spec(self) -> StartSpec:
        """The start as it was asked for: the corner index, or the explicit cell."""
        return self.start if self.start_index is None else self.start_index


def run_episode(
    world: World,
    method_name: str,
    predictor: Predictor | None,
    start: StartSpec = 0,
    seed: int = 0,
    config: ExplorationConfig | None = None,
    on_step: StepListener | None = None,
    source: StepSource | None = None,
    robot: int = 0,
) -> EpisodeResult:
    """Explore `world` from `start` (a corner 0-3 or a cell) for `config.steps` steps.

    `source` (default: an in-process `Simulator` with the robot at that start) moves robot
    `robot` and scans; a world process must have placed that robot at the same start.
    A start the world cannot take raises WorldError.
    """
    config = config or ExplorationConfig()
    start = normalise_start(start)
    world.check_size(config.world.max_cells)
    cell = start_cell(world, start, config.world.start_clearance_cells)
    began = time.perf_counter()
    if source is None:
        source, robot = Simulator(world, [cell], config.sensor, config.motion), 0
    method = make_method(method_name, config)
    explorer = Explorer(world.shape, method, predictor, config, seed)
    recorder = MetricRecorder(world, cell, predictor, config.metrics)
    explorer.observe(source.scan(robot))
    trajectory = [explorer.pose.copy()]
    finished_at = None
    end_reason = "budget"
    for t in range(config.steps + 1):
        if recorder.at_step(t, explorer.observed, config.until_iou) and t < config.steps:
            finished_at, end_reason = t, IOU_REACHED
            recorder.hold_to_end(t, config.steps, explorer.observed)
            break
        if t == config.steps:
            break
        motion = explorer.next_motion(t)
        if motion is None:
            finished_at, end_reason = t, explorer.end_reason
            recorder.hold_to_end(t, config.steps, explorer.observed)
            break
        explorer.observe(source.step(robot, motion))
        trajectory.append(explorer.pose.copy())
        if on_step is not None:
            on_step(t + 1, explorer, recorder)
    recorder.flush()
    return EpisodeResult(
        world=world.name,
        method=method_name,
        predictor=predictor.name if predictor is not None else None,
        start_index=start if isinstance(start, int) else None,
        start=cell,
        seed=seed,
        steps=config.steps,
        curves=recorder.curves,
        trajectory=np.asarray(trajectory, dtype=np.int64),
        finished_at=finished_at,
        end_reason=end_reason,
        stats=explorer.stats,
        final_observed=explorer.observed.copy(),
        final_prediction=recorder.last_prediction,
        wall_time_s=time.perf_counter() - began,
        config=config,
        degraded_samples=recorder.degraded_samples,
        metric_workers=recorder.member_workers,
        snapshots=recorder.snapshots,
    )
