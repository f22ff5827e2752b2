"""Samples the metrics of one run (docs/algorithms.md#metrics): coverage and IoU every 50 steps,
TU every 100, and the first step at which coverage and IoU reach each of
`MetricsConfig.reach_levels` (docs/algorithms.md#time-to-level); says when a run may stop
(`until_iou`, `metrics.until_coverage`).

IoU and TU judge the map the robot would hand over: P_t = known cells of O_t,
unknown cells from the main predictor G thresholded at 0.5 (with no predictor,
unknown counts as free). When a distributed pool cannot deliver G for a sample,
unknown counts as free for that sample and the step is listed in `degraded_samples`.
At `MetricsConfig.snapshot_steps` the recorder keeps O_t and G's map for the report.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from mapex.config import MetricsConfig
from mapex.grid import UNKNOWN, Cell, observed_to_probability
from mapex.metrics import (
    building_footprint,
    coverage,
    occupied_iou,
    predicted_occupancy,
    topological_understanding,
    tu_goals,
)
from mapex.prediction.base import EnsemblePrediction, Predictor
from mapex.worlds.base import World

IOU_REACHED = "iou_reached"  # the run ended because G's IoU reached `config.until_iou`
# the run ended because coverage reached `metrics.until_coverage`
COVERAGE_REACHED = "coverage_reached"


@dataclass
class MetricCurves:
    """Sampled curves of one run; `tu` is NaN at steps where TU is not sampled."""

    steps: list[int] = field(default_factory=list)
    coverage: list[float] = field(default_factory=list)
    iou: list[float] = field(default_factory=list)
    tu: list[float] = field(default_factory=list)

    # metric -> level -> the first step at which it was reached (None: not yet, censored)
    reached: dict[str, dict[float, int | None]] = field(default_factory=dict)

    def auc(self) -> dict[str, float]:
        """Mean of each curve over its samples (docs/algorithms.md#metrics)."""
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
        self.curves.reached = {
            metric: dict.fromkeys(config.reach_levels) for metric in ("coverage", "iou")
        }
        self.reach = StepTracker(world.valid_space)
        self.last_prediction: np.ndarray | None = None
        self.degraded_samples: list[int] = []
        self.member_workers: list[tuple[int, dict[str, str]]] = []  # (t, who answered G)
        self.snapshots: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}  # t -> (O_t, G)
        self._pending: tuple[int, np.ndarray, Callable[[], EnsemblePrediction] | None] | None = None

    def is_sample_step(self, t: int) -> bool:
        return t % self.config.sample_every_steps == 0

    def at_step(self, t: int, observed: np.ndarray, until_iou: float | None = None) -> str | None:
        """Step `t`'s metrics of O_t (every step: coverage levels; sample steps: the samples).
        Why the run may end here, or None: IOU_REACHED when `until_iou` is given and G's IoU
        has reached it at this step's sample, COVERAGE_REACHED when coverage has reached
        `metrics.until_coverage`."""
        coverage_now = self.reach.track(t, observed)
        if self._pending is not None and t - self._pending[0] >= self.config.complete_after_steps:
            self.flush()  # the sample taken `complete_after_steps` ago: published now
        for level, step in self.curves.reached["coverage"].items():
            if step is None and coverage_now >= level:
                self.curves.reached["coverage"][level] = t
        enough = self.config.until_coverage
        stop = COVERAGE_REACHED if enough is not None and coverage_now >= enough else None
        if not self.is_sample_step(t):
            return stop
        self.record(t, observed)
        if until_iou is None:
            return stop
        self.flush()
        return IOU_REACHED if self.curves.iou[-1] >= until_iou else stop

    def record(self, t: int, observed: np.ndarray) -> None:
        """Sample every metric due at step `t` for the observed map O_t.

        G's whole-map prediction for the sample is asked for now and used when the sample
        is completed, `metrics.complete_after_steps` later (or by the next `record` or
        `flush`): a remote ensemble computes it while exploration goes on (the numbers are
        the same either way).
        """
        self.flush()
        observed = observed.copy()
        later = None
        if self.predictor is not None:
            later = self.predictor.predict_later(observed, members=(0,))
        self._pending = (t, observed, later)

    def flush(self) -> None:
        """Complete the sample `record` started, if any."""
        if self._pending is None:
            return
        t, observed, later = self._pending
        self._pending = None
        main = self._main_map(t, observed, None if later is None else later())
        self.last_prediction = main
        cov, iou, tu = self._measure(observed, main, t % self.config.tu_every_steps == 0)
        self._note_iou_levels(t, iou)
        self._append(t, cov, iou, tu)
        self._keep_snapshot(t, observed)
        self.reach.complete(t)

    def _note_iou_levels(self, t: int, iou: float) -> None:
        """Levels first reached by the sample at `t`: the first step since the previous
        sample at which they were reached, measuring every step in between
        (docs/algorithms.md#time-to-level)."""
        levels = self.curves.reached["iou"]
        new = sorted(level for level, step in levels.items() if step is None and iou >= level)
        for level in new:
            levels[level] = t
        for step, observed in self.reach.window(until=t):
            if not new:
                return
            main = self._main_map(step, observed, self._predict_now(observed))
            between = occupied_iou(
                predicted_occupancy(observed, main, self.config.prediction_threshold),
                self.world.occupancy,
                self.footprint,
            )
            while new and between >= new[0]:
                levels[new.pop(0)] = step

    def _predict_now(self, observed: np.ndarray) -> EnsemblePrediction | None:
        if self.predictor is None:
            return None
        return self.predictor.predict(observed, members=(0,))

    def hold_to_end(self, t_end: int, steps: int, observed: np.ndarray) -> None:
        """Early termination at `t_end`: the map no longer changes, so every later sample
        (to `steps`) holds the end state's values."""
        self.flush()
        later = [t for t in range(t_end + 1, steps + 1) if self.is_sample_step(t)]
        if not later:
            return
        prediction = None
        if self.predictor is not None:
            prediction = self.predictor.predict(observed, members=(0,))
        main = self._main_map(t_end, observed, prediction)
        self.last_prediction = main
        cov, iou, tu = self._measure(observed, main, with_tu=True)
        if not self.is_sample_step(t_end):
            self._note_iou_levels(t_end, iou)
        for t in later:
            self._append(t, cov, iou, tu if t % self.config.tu_every_steps == 0 else float("nan"))
            self._keep_snapshot(t, observed)

    def _keep_snapshot(self, t: int, observed: np.ndarray) -> None:
        if t in self.config.snapshot_steps:
            main = None if self.predictor is None else self.last_prediction
            self.snapshots[t] = (observed.copy(), main)

    def _measure(
        self, observed: np.ndarray, main: np.ndarray, with_tu: bool
    ) -> tuple[float, float, float]:
        occupied = predicted_occupancy(observed, main, self.config.prediction_threshold)
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

    def _main_map(
        self, t: int, observed: np.ndarray, prediction: EnsemblePrediction | None
    ) -> np.ndarray:
        """G's whole-map prediction (known cells copied through), or, without a predictor
        or when G did not answer, the observed map with unknown cells counted as free."""
        if prediction is not None and prediction.workers is not None:
            self.member_workers.append((t, prediction.served_by()))
        if prediction is not None and prediction.answered == (0,):
            main = prediction.main
        else:
            if prediction is not None:
                self.degraded_samples.append(t)
            main = np.where(observed == UNKNOWN, 0, observed_to_probability(observed))
            main = main.astype(np.float32)
        return main


class StepTracker:
    """Coverage at every step, and the observed maps since the last completed metric sample
    (kept as per-step changes, so a step between two samples can be measured afterwards)."""

    def __init__(self, valid_space: np.ndarray) -> None:
        self.valid = np.ascontiguousarray(valid_space, dtype=bool).ravel()
        self.n_valid = max(int(self.valid.sum()), 1)
        self._shape = valid_space.shape
        self._last: np.ndarray | None = None  # O of the last tracked step, flat
        self._known_valid = 0
        self._base: np.ndarray | None = None  # O at the last completed sample, flat
        self._changes: list[tuple[int, np.ndarray, np.ndarray]] = []  # (t, cells, values)

    def track(self, t: int, observed: np.ndarray) -> float:
        """Note O_t (steps in increasing order); return its coverage."""
        flat = observed.ravel()
        if self._last is None:
            self._last, self._base = flat.copy(), flat.copy()
            self._known_valid = int(np.count_nonzero((flat != UNKNOWN) & self.valid))
            return self._known_valid / self.n_valid
        cells = np.flatnonzero(flat != self._last)
        was_known = self._last[cells] != UNKNOWN
        now_known = flat[cells] != UNKNOWN
        valid = self.valid[cells]
        self._known_valid += int(np.count_nonzero(valid & now_known & ~was_known))
        self._known_valid -= int(np.count_nonzero(valid & was_known & ~now_known))
        self._last[cells] = flat[cells]
        self._changes.append((t, cells, flat[cells].copy()))
        return self._known_valid / self.n_valid

    def window(self, until: int) -> Iterator[tuple[int, np.ndarray]]:
        """(t, O_t) for every tracked step after the last completed sample and before
        `until`, in order (the map yielded is reused: copy it to keep it)."""
        if self._base is None:
            return
        current = self._base.copy()
        for t, cells, values in self._changes:
            if t >= until:
                return
            current[cells] = values
            yield t, current.reshape(self._shape)

    def complete(self, t: int) -> None:
        """The sample at step `t` is complete: later windows start from O_t."""
        if self._base is None:
            return
        for _, cells, values in (change for change in self._changes if change[0] <= t):
            self._base[cells] = values
        self._changes = [change for change in self._changes if change[0] > t]
