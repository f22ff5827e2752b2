"""The predictor interface shared by the classical and learned ensembles.

A predictor maps an observed map O_t (uint8 codes of `mapex.grid`) to one
occupancy-probability map per ensemble member. Member 0 is the main model G,
members 1.. are G_1..G_n. Known cells are always copied through from O_t, so
only unknown cells carry a prediction.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from mapex.grid import UNKNOWN, observed_to_probability

Region = tuple[int, int, int, int]  # row_start, row_stop, col_start, col_stop (slice bounds)


@dataclass(frozen=True)
class EnsemblePrediction:
    """Member predictions, float32 (n_members, rows, cols); member 0 is G."""

    members: np.ndarray

    @property
    def main(self) -> np.ndarray:
        """P_t = G(O_t)."""
        return self.members[0]

    @property
    def mean(self) -> np.ndarray:
        """M_t, the mean over members."""
        return self.members.mean(axis=0, dtype=np.float32)

    @property
    def variance(self) -> np.ndarray:
        """V_t, the unbiased variance over members (zeros with fewer than two)."""
        if len(self.members) < 2:
            return np.zeros(self.members.shape[1:], dtype=np.float32)
        return self.members.var(axis=0, ddof=1, dtype=np.float32)


class Predictor(ABC):
    """An ensemble of map predictors; subclasses implement `predict_members`."""

    name: str = "predictor"
    n_members: int = 4

    @abstractmethod
    def predict_members(self, observed: np.ndarray) -> np.ndarray:
        """Raw member outputs, float32 (n_members, rows, cols) in [0, 1], for a map crop."""

    def predict(self, observed: np.ndarray, region: Region | None = None) -> EnsemblePrediction:
        """Predict every member on `region` of `observed` (whole map if None).

        Outside the region the members keep the observed map (unknown = 0.5, so
        zero variance); inside, known cells are copied through from O_t.
        """
        known_prob = observed_to_probability(observed)
        members = np.repeat(known_prob[None], self.n_members, axis=0)
        r0, r1, c0, c1 = (
            region if region is not None else (0, observed.shape[0], 0, observed.shape[1])
        )
        crop = observed[r0:r1, c0:c1]
        raw = self.predict_members(crop)
        unknown = crop == UNKNOWN
        members[:, r0:r1, c0:c1] = np.where(unknown[None], raw, known_prob[None, r0:r1, c0:c1])
        return EnsemblePrediction(members.astype(np.float32, copy=False))

    def predict_main(self, observed: np.ndarray) -> np.ndarray:
        """G's whole-map prediction with known cells copied through (what the metrics judge)."""
        return self.predict(observed).main


def known_region(observed: np.ndarray, margin_cells: int) -> Region:
    """Bounding box of the known cells grown by `margin_cells` (e.g. the sensor range), clipped."""
    rows, cols = np.nonzero(observed != UNKNOWN)
    if rows.size == 0:
        return (0, observed.shape[0], 0, observed.shape[1])
    return (
        max(int(rows.min()) - margin_cells, 0),
        min(int(rows.max()) + margin_cells + 1, observed.shape[0]),
        max(int(cols.min()) - margin_cells, 0),
        min(int(cols.max()) + margin_cells + 1, observed.shape[1]),
    )
