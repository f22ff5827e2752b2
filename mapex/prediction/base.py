"""The predictor interface shared by the classical and learned ensembles.

A predictor maps an observed map O_t (uint8 codes of `mapex.grid`) to one
occupancy-probability map per ensemble member. Member 0 is the main model G,
members 1.. are G_1..G_n. Known cells are always copied through from O_t, so
only unknown cells carry a prediction. Member outputs are quantised to the uint8
levels of `mapex.grid.quantise_probability`, the precision they have on the wire.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from mapex.grid import (
    UNKNOWN,
    dequantise_probability,
    observed_to_probability,
    quantise_probability,
)

Region = tuple[int, int, int, int]  # row_start, row_stop, col_start, col_stop (slice bounds)
MEMBER_NAMES = ("g", "g1", "g2", "g3")  # ensemble members by index; member 0 is the main model G


@dataclass(frozen=True)
class EnsemblePrediction:
    """Member predictions, float32 (n_members, rows, cols); member 0 is G.

    P_t is G's row; M_t and V_t are the mean and variance over G_1..G_n only, as in the paper
    (docs/algorithms.md#prediction): G, trained on all the data, is not one of the members whose
    disagreement measures the uncertainty. Only `region` was predicted: outside it every member
    holds the observed map, so the mean is that map and the variance is zero there. `member_ids`
    names the member of each row (None: rows 0..n-1 are members 0..n-1). A distributed pool may
    answer with fewer members than asked (docs/design.md#reliability); then `member_ids` says
    which, and row 0 is G only if G answered."""

    members: np.ndarray
    region: Region | None = None
    member_ids: tuple[int, ...] | None = None
    workers: tuple[str, ...] | None = None  # the worker that served each row, when remote

    @property
    def answered(self) -> tuple[int, ...]:
        """The member index of each row."""
        return self.member_ids if self.member_ids is not None else tuple(range(len(self.members)))

    def served_by(self) -> dict[str, str]:
        """{member name: id of the worker that answered it} (empty when computed locally),
        so a run's record says who produced every prediction it used."""
        if self.workers is None:
            return {}
        return {
            MEMBER_NAMES[k]: worker for k, worker in zip(self.answered, self.workers, strict=True)
        }

    @property
    def has_variance(self) -> bool:
        """Whether enough of G_1..G_n answered for a variance (at least two)."""
        return len(self._ensemble_rows()) >= 2

    @property
    def main(self) -> np.ndarray:
        """P_t = G(O_t)."""
        return self.members[0]

    @cached_property
    def mean(self) -> np.ndarray:
        """M_t, the mean over G_1..G_n (G's prediction when none of them answered)."""
        rows = self._ensemble_rows() or list(range(len(self.members)))
        mean = self.members[0].copy()
        window = self._window()
        mean[window] = self.members[(rows, *window)].mean(axis=0, dtype=np.float32)
        return mean

    @cached_property
    def variance(self) -> np.ndarray:
        """V_t, the unbiased variance over G_1..G_n (zeros with fewer than two)."""
        variance = np.zeros(self.members.shape[1:], dtype=np.float32)
        rows = self._ensemble_rows()
        if len(rows) >= 2:
            window = self._window()
            deviations = self.members[(rows, *window)] - self.mean[window]
            variance[window] = np.einsum("kij,kij->ij", deviations, deviations) / np.float32(
                len(rows) - 1
            )
        return variance

    def with_known(self, observed: np.ndarray) -> EnsemblePrediction:
        """This prediction with the known cells of a later map `observed` copied through,
        as `predict` does for its own map: cells observed since are certain (zero variance),
        the others keep what was predicted."""
        known = observed != UNKNOWN
        members = np.where(known[None], observed_to_probability(observed)[None], self.members)
        return EnsemblePrediction(members, self.region, self.member_ids, self.workers)

    def _ensemble_rows(self) -> list[int]:
        """The rows holding G_1..G_n."""
        return [row for row, member in enumerate(self.answered) if member != 0]

    def _window(self) -> tuple[slice, slice]:
        r0, r1, c0, c1 = self.region or (0, self.members.shape[1], 0, self.members.shape[2])
        return slice(r0, r1), slice(c0, c1)


class Predictor(ABC):
    """An ensemble of map predictors; subclasses implement `predict_members`.

    `context_cells`: the members see this much more map around a region than they
    are asked to predict, so that a region's edge inside the map does not look like
    the map's border to them.
    """

    name: str = "predictor"
    n_members: int = 4
    context_cells: int = 0

    @abstractmethod
    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """Raw outputs of the chosen members, float32 (len(members), rows, cols) in [0, 1],
        for a map crop."""

    def predict(
        self,
        observed: np.ndarray,
        region: Region | None = None,
        members: Sequence[int] | None = None,
    ) -> EnsemblePrediction:
        """Predict the chosen members (all if None) on `region` of `observed` (whole map if None).
        Outside the region the members keep the observed map (unknown = 0.5, so
        zero variance); inside, known cells are copied through from O_t.
        """
        members = tuple(range(self.n_members)) if members is None else tuple(members)
        w0, w1, v0, v1 = self.members_window(observed.shape, region)
        view = observed[w0:w1, v0:v1]
        raw = self.predict_members(view, members)
        if raw.shape != (len(members), *view.shape):
            raise ValueError(f"{self.name}: members returned {raw.shape}, expected {view.shape}")
        return assemble_prediction(observed, region, raw, members, self.context_cells)

    def members_window(self, shape: tuple[int, int], region: Region | None) -> Region:
        """The part of a map of `shape` the members see to predict `region` (whole map if
        None): the region with `context_cells` of map around it."""
        return with_context(region or (0, shape[0], 0, shape[1]), shape, self.context_cells)

    def predict_later(
        self,
        observed: np.ndarray,
        region: Region | None = None,
        members: Sequence[int] | None = None,
    ) -> Callable[[], EnsemblePrediction]:
        """`predict`, as a function to call for the result. In one process it is computed
        now; a remote ensemble starts the work and lets the caller go on meanwhile."""
        prediction = self.predict(observed, region, members)
        return lambda: prediction

    def predict_main(self, observed: np.ndarray) -> np.ndarray:
        """G's whole-map prediction with known cells copied through (what the metrics judge)."""
        return self.predict(observed, members=(0,)).main

    def wait(self, timeout_s: float) -> bool:
        """Wait until every member can answer; False if that did not happen in `timeout_s`.
        An in-process ensemble always can."""
        return True

    def close(self) -> None:  # noqa: B027 (a no-op in one process, not abstract)
        """Release what the ensemble holds (nothing in one process)."""

    def __enter__(self) -> Predictor:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def assemble_prediction(
    observed: np.ndarray,
    region: Region | None,
    raw: np.ndarray,
    members: Sequence[int],
    context_cells: int,
    workers: tuple[str, ...] | None = None,
) -> EnsemblePrediction:
    """The ensemble prediction from the members' raw outputs on their window of `region`
    (the region with `context_cells` of map around it): outputs quantised to the wire's
    levels, known cells copied through, the observed map outside the region. One function
    for the in-process and the distributed ensembles, so both give the same numbers."""
    window = region or (0, observed.shape[0], 0, observed.shape[1])
    r0, r1, c0, c1 = window
    w0, _, v0, _ = with_context(window, observed.shape, context_cells)
    known_prob = observed_to_probability(observed)
    stacked = np.repeat(known_prob[None], len(members), axis=0)
    crop_raw = raw[:, r0 - w0 : r1 - w0, c0 - v0 : c1 - v0]
    crop_raw = dequantise_probability(quantise_probability(crop_raw))
    unknown = observed[r0:r1, c0:c1] == UNKNOWN
    stacked[:, r0:r1, c0:c1] = np.where(unknown[None], crop_raw, known_prob[None, r0:r1, c0:c1])
    return EnsemblePrediction(stacked, region, tuple(members), workers)


def with_context(region: Region, shape: tuple[int, int], context_cells: int) -> Region:
    """`region` grown by `context_cells` on every side, clipped to a map of `shape`."""
    r0, r1, c0, c1 = region
    return (
        max(r0 - context_cells, 0),
        min(r1 + context_cells, shape[0]),
        max(c0 - context_cells, 0),
        min(c1 + context_cells, shape[1]),
    )


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
