"""Samples the metrics of one run (SPEC §6): coverage and IoU every 50 steps, TU every 100.

IoU and TU judge the map the robot would hand over: P_t = known cells of O_t,
unknown cells from the main predictor G thresholded at 0.5 (with no predictor,
unknown counts as free).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mapex.config import MetricsConfig
from mapex.grid import Cell
from mapex.metrics import (
    building_footprint,
    coverage,
    occupied_iou,
    predicted_occupancy,
    topological_understanding,
    tu_goals,
)
from mapex.prediction.base import Predictor
from mapex.worlds.base import World


@dataclass
class MetricCurves:
    """Sampled curves of one run; `tu` is NaN at steps where TU is not sampled."""

    steps: list[int] = field(default_factory=list)
    coverage: list[float] = field(default_factory=list)
    iou: list[float] = field(default_factory=list)
    tu: list[float] = field(default_factory=list)

    def auc(self) -> dict[str, float]:
        """Mean of each curve over its samples (SPEC §6 aggregate)."""
        tu = np.asarray(self.tu, dtype=np.float64)
        return {
            "coverage": float(np.mean(self.coverage)),
            "iou": float(np.mean(self.iou)),
            "tu": float(np.nanmean(tu)) if np.isfinite(tu).any() else float("nan"),
        }


class MetricRecorder:
    """Computes and stores the metric samples of one run."""

    def __init__(
        self, world: World, start: Cell, predictor: Predictor | None, config: MetricsConfig
    ) -> None:
        self.world = world
        self.start = start
        self.predictor = predictor
        self.config = config
        self.footprint = building_footprint(world.valid_space, config.footprint_margin_cells)
        self.goals = tu_goals(
            world.name, world.occupancy, world.valid_space, start, config.tu_goals
        )
        self.curves = MetricCurves()
        self.last_prediction: np.ndarray | None = None

    def is_sample_step(self, t: int) -> bool:
        return t % self.config.sample_every_steps == 0

    def record(self, t: int, observed: np.ndarray) -> None:
        """Sample every metric due at step `t` for the observed map O_t."""
        self._append(t, *self._measure(observed, with_tu=t % self.config.tu_every_steps == 0))

    def hold_to_end(self, t_end: int, steps: int, observed: np.ndarray) -> None:
        """Early termination at `t_end`: the map no longer changes, so every later sample
        (to `steps`) holds the end state's values."""
        later = [t for t in range(t_end + 1, steps + 1) if self.is_sample_step(t)]
        if not later:
            return
        cov, iou, tu = self._measure(observed, with_tu=True)
        for t in later:
            self._append(t, cov, iou, tu if t % self.config.tu_every_steps == 0 else float("nan"))

    def _measure(self, observed: np.ndarray, with_tu: bool) -> tuple[float, float, float]:
        occupied = self.predicted_map(observed)
        cov = coverage(observed, self.world.valid_space)
        iou = occupied_iou(occupied, self.world.occupancy, self.footprint)
        tu = float("nan")
        if with_tu:
            tu = topological_understanding(occupied, self.world.occupancy, self.start, self.goals)
        return cov, iou, tu

    def _append(self, t: int, cov: float, iou: float, tu: float) -> None:
        self.curves.steps.append(t)
        self.curves.coverage.append(cov)
        self.curves.iou.append(iou)
        self.curves.tu.append(tu)

    def predicted_map(self, observed: np.ndarray) -> np.ndarray:
        """bool P_t thresholded: known cells from O_t, unknown ones from G's full-map prediction."""
        if self.predictor is None:
            main = np.zeros(observed.shape, dtype=np.float32)
        else:
            main = self.predictor.predict_main(observed)
        self.last_prediction = main
        return predicted_occupancy(observed, main, self.config.prediction_threshold)
