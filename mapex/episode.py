"""One exploration episode in one process: world + method + predictor + seed -> record.

The loop is the same lockstep the distributed services run: the simulator
answers each step with a scan, the explorer integrates it and chooses the next
motion. Deterministic for a given world, start, method, predictor and seed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mapex.config import ExplorationConfig
from mapex.explorer import Explorer, ExplorerStats
from mapex.grid import Cell
from mapex.methods import make_method
from mapex.prediction.base import Predictor
from mapex.recorder import MetricCurves, MetricRecorder
from mapex.simulator import Simulator
from mapex.worlds import World, start_poses


@dataclass
class EpisodeResult:
    """Everything a run produces: curves, trajectory, final maps and counters."""

    world: str
    method: str
    predictor: str | None
    start_index: int
    start: Cell
    seed: int
    steps: int
    curves: MetricCurves
    trajectory: np.ndarray  # int (n + 1, 2): pose after the initial scan, then after each step
    finished_at: int | None  # step at which no frontier was left (early termination)
    stats: ExplorerStats
    final_observed: np.ndarray
    final_prediction: np.ndarray | None  # G's whole-map prediction at the end
    wall_time_s: float = 0.0
    config: ExplorationConfig = field(default_factory=ExplorationConfig)


def run_episode(
    world: World,
    method_name: str,
    predictor: Predictor | None,
    start_index: int = 0,
    seed: int = 0,
    config: ExplorationConfig | None = None,
    on_step: Callable[[int], None] | None = None,
) -> EpisodeResult:
    """Explore `world` from start `start_index` (0-3) for `config.steps` steps."""
    config = config or ExplorationConfig()
    starts = start_poses(world, config.world.start_clearance_cells)
    if not 0 <= start_index < len(starts):
        raise ValueError(f"start index {start_index} out of range 0..{len(starts) - 1}")
    start = starts[start_index]
    began = time.perf_counter()
    simulator = Simulator(world, [start], config.sensor, config.motion)
    method = make_method(method_name, config)
    explorer = Explorer(world.shape, method, predictor, config, seed)
    recorder = MetricRecorder(world, start, predictor, config.metrics)
    explorer.observe(simulator.scan(0))
    trajectory = [explorer.pose.copy()]
    finished_at = None
    for t in range(config.steps + 1):
        if recorder.is_sample_step(t):
            recorder.record(t, explorer.observed)
        if t == config.steps:
            break
        motion = explorer.next_motion(t)
        if motion is None:
            finished_at = t
            recorder.hold_to_end(t, config.steps, explorer.observed)
            break
        explorer.observe(simulator.step(0, motion))
        trajectory.append(explorer.pose.copy())
        if on_step is not None:
            on_step(t + 1)
    return EpisodeResult(
        world=world.name,
        method=method_name,
        predictor=predictor.name if predictor is not None else None,
        start_index=start_index,
        start=start,
        seed=seed,
        steps=config.steps,
        curves=recorder.curves,
        trajectory=np.asarray(trajectory, dtype=np.int64),
        finished_at=finished_at,
        stats=explorer.stats,
        final_observed=explorer.observed.copy(),
        final_prediction=recorder.last_prediction,
        wall_time_s=time.perf_counter() - began,
        config=config,
    )
