"""One ensemble prediction per epoch for the whole team (docs/algorithms.md#teams).

Every robot of a team re-plans on the same shared map, but at its own steps, so N robots
ask for about N times the predictions of one robot, and prediction is most of a re-plan's
cost. With `team.prediction_epoch_steps` = k > 1 the team predicts on its map as it stood
at the start of the current epoch (the last step t with t % k == 0): every robot that
re-plans within the epoch uses that one prediction, with the cells observed since copied
through. With k = 1 that is the current map, as a single robot predicts, computed once
for the robots re-planning at the same step. The epoch's map depends on the step alone,
so robots decided in other processes ask the predictor pool for the very same crop, which
a worker answers once (`services.predictor`'s recent answers), and a team run stays
deterministic for a seed.
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
        self._prediction: EnsemblePrediction | None = None

    def begin_step(self, t: int, observed: np.ndarray) -> None:
        """Called with the shared map before the robots decide step t."""
        if self._epoch_map is None or t % self.epoch_steps == 0:
            self._epoch_map, self._prediction = observed.copy(), None

    def prediction(self, observed: np.ndarray) -> EnsemblePrediction:
        """The epoch's prediction with the known cells of `observed` (the map now)."""
        if self._epoch_map is None:
            raise RuntimeError("begin_step was not called")
        if self._prediction is None:
            region = known_region(self._epoch_map, self.margin_cells)
            self._prediction = self.predictor.predict(self._epoch_map, region)
        return self._prediction.with_known(observed)


class TeammateExplorer(Explorer):
    """An explorer whose re-plans use the team's epoch prediction."""

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

    def predict(self) -> EnsemblePrediction:
        if self.shared is None:
            return super().predict()  # raises: the method needs a predictor
        return self.shared.prediction(self.observed)
