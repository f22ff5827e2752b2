"""One ensemble prediction per epoch for the whole team (docs/algorithms.md#teams), and the
explorer of a robot of a team.

N robots re-planning at their own steps would ask for about N times the predictions of one
robot. With `team.prediction_epoch_steps` = k the team predicts on its map as it stood at
the start of the current epoch (the last step t with t % k == 0), with the cells observed
since copied through; k = 1 is the current map, computed once for the robots re-planning at
the same step. The epoch's map depends on the step alone, so planners in other processes
ask the predictor pool for the very same crop, which a worker answers once (its recent
answers, `services.predictor`), and a team run stays deterministic for a seed.
"""

from __future__ import annotations

import numpy as np

from mapex.config import ExplorationConfig
from mapex.explorer import Explorer
from mapex.methods.base import Method
from mapex.prediction.base import EnsemblePrediction, Predictor, known_region


class EpochPrediction:
    """The team's prediction of the current epoch, made on first use."""

    def __init__(self, predictor: Predictor, epoch_steps: int, margin_cells: int) -> None:
        self.predictor = predictor
        self.epoch_steps = epoch_steps
        self.margin_cells = margin_cells  # the known area plus this is predicted (sensor range)
        self._epoch_map: np.ndarray | None = None
        self._predictions: dict[tuple[int, ...], EnsemblePrediction] = {}  # by members

    def begin_step(self, t: int, observed: np.ndarray) -> None:
        """Called with the shared map before the robots decide step t."""
        if self._epoch_map is None or t % self.epoch_steps == 0:
            self._epoch_map, self._predictions = observed.copy(), {}

    def prediction(self, observed: np.ndarray, members: tuple[int, ...]) -> EnsemblePrediction:
        """The epoch's prediction of `members` with the known cells of `observed` (the map
        now)."""
        if self._epoch_map is None:
            raise RuntimeError("begin_step was not called")
        if members not in self._predictions:
            region = known_region(self._epoch_map, self.margin_cells)
            self._predictions[members] = self.predictor.predict(self._epoch_map, region, members)
        prediction = self._predictions[members]
        if np.array_equal(observed, self._epoch_map):  # nothing known since: as it is
            return prediction
        return prediction.with_known(observed)


class TeammateExplorer(Explorer):
    """An explorer whose re-plans use the team's epoch prediction; it also re-plans when
    its method says the team re-plans in step (`Method.replans_at`), and when its method
    chose to wait it stands still for `team.idle_replan_steps` before looking again."""

    def __init__(
        self,
        shape: tuple[int, int],
        method: Method,
        shared: EpochPrediction | None,
        config: ExplorationConfig,
        seed: int,
    ) -> None:
        super().__init__(shape, method, None if shared is None else shared.predictor, config, seed)
        self.shared = shared
        self.waiting_until: int | None = None  # the step at which a waiting robot looks again

    def next_motion(self, t: int) -> np.ndarray | None:
        if self.method.replans_at(t):
            self.goal = self.path = None
        elif self.waiting_until is not None and t < self.waiting_until:
            return None
        self.method.waiting = False
        motion = super().next_motion(t)
        waits = motion is None and self.method.waiting
        self.waiting_until = t + self.config.team.idle_replan_steps if waits else None
        return motion

    def predict(self) -> EnsemblePrediction:
        if self.shared is None:
            return super().predict()  # raises: the method needs a predictor
        members = self.method.prediction_members(self.predictor.n_members)
        return self.shared.prediction(self.observed, members)
