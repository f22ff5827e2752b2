"""The oracle: the ground truth as the prediction (docs/algorithms.md#the-oracle).

An upper bound of what any prediction can buy a method, not a predictor a robot could have:
it reads the world's walls. P_t = M_t = the true walls on the unknown cells of the predicted
region (known cells copied from O_t as always); V_t = 1 on every cell of the region still
unknown in O_t and 0 elsewhere, so MapEx's variance-weighted gain is the number of unknown
cells a frontier truly sees: the exact information gain. An unbiased variance of member
values in [0, 1] is never 1, so `OraclePrediction` says what V_t is instead of computing it
from members; and it answers every member asked, so a re-plan under the oracle is never
degraded. `oracle_prediction` builds it for the in-process `OraclePredictor` and for the
distributed oracle (services/ensemble_client.py) alike, so both give the same numbers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from mapex.grid import UNKNOWN, Cell, observed_to_probability
from mapex.prediction.base import MEMBER_NAMES, EnsemblePrediction, Predictor, Region

ORACLE = "oracle"  # its name in `mapex.prediction.PREDICTORS` and in every run record


@dataclass(frozen=True)
class OraclePrediction(EnsemblePrediction):
    """The ground truth as an ensemble prediction: every row holds the same map (the truth on
    the region's unknown cells), `unknown` marks the cells of the region still unknown in O_t
    (V_t is 1 there, 0 elsewhere). `workers`, when remote, names the oracle worker once per
    row (it answered them all with one truth)."""

    unknown: np.ndarray | None = None  # bool (rows, cols); required

    def __post_init__(self) -> None:
        if self.unknown is None or self.unknown.shape != self.members.shape[1:]:
            raise ValueError("an oracle prediction needs the mask of its unknown cells")
        if len(self.members) == 0:
            raise ValueError("an oracle prediction needs at least one member row")

    @property
    def has_variance(self) -> bool:
        """Always: V_t is known exactly, whichever members were asked."""
        return True

    @cached_property
    def mean(self) -> np.ndarray:
        """M_t = P_t: the truth on the region's unknown cells, O_t elsewhere."""
        return self.members[0]

    @cached_property
    def variance(self) -> np.ndarray:
        """V_t: 1 on the region's cells still unknown, 0 on every other cell."""
        return self.unknown.astype(np.float32)

    def served_by(self) -> dict[str, str]:
        """{"g": the oracle worker} when remote (it serves member g only), else empty."""
        return {} if self.workers is None else {MEMBER_NAMES[0]: self.workers[0]}

    def with_known(self, observed: np.ndarray) -> OraclePrediction:
        """This prediction with the known cells of a later map `observed` copied through:
        they are certain now (V_t 0 there), the others keep the truth."""
        known = observed != UNKNOWN
        single = np.where(known, observed_to_probability(observed), self.members[0])
        members = np.repeat(single[None].astype(np.float32), len(self.members), axis=0)
        return OraclePrediction(
            members, self.region, self.member_ids, self.workers, self.unknown & ~known
        )


def oracle_prediction(
    observed: np.ndarray,
    walls: np.ndarray,
    origin: Cell,
    region: Region | None,
    members: Sequence[int],
    worker: str | None = None,
) -> OraclePrediction:
    """The oracle's prediction of `members` on `region` of `observed` (whole map if None).

    `walls`: the truth (bool, or float 0/1) of a window of the map whose top-left cell is
    `origin` and which covers the region; `worker`: the oracle worker that sent it (remote).
    ValueError when no member is asked or the window does not cover the region."""
    members = tuple(members)
    if not members:
        raise ValueError("the oracle was asked for no member")
    r0, r1, c0, c1 = region or (0, observed.shape[0], 0, observed.shape[1])
    top, left = origin
    rows, cols = walls.shape
    if not (top <= r0 and left <= c0 and r1 <= top + rows and c1 <= left + cols):
        raise ValueError(
            f"the truth window at {tuple(origin)} of shape {walls.shape} does not cover the "
            f"region {(r0, r1, c0, c1)}"
        )
    truth = np.asarray(walls[r0 - top : r1 - top, c0 - left : c1 - left], dtype=np.float32)
    single = observed_to_probability(observed)
    unknown = np.zeros(observed.shape, dtype=bool)
    unknown[r0:r1, c0:c1] = observed[r0:r1, c0:c1] == UNKNOWN
    single[r0:r1, c0:c1] = np.where(unknown[r0:r1, c0:c1], truth, single[r0:r1, c0:c1])
    stacked = np.repeat(single[None], len(members), axis=0)
    workers = None if worker is None else (worker,) * len(members)
    return OraclePrediction(stacked, region, members, workers, unknown)


class OraclePredictor(Predictor):
    """The ground truth of one world as the prediction: an upper bound, not a predictor a robot
    could have. Built from the world's walls (`World.occupancy`)."""

    name = ORACLE
    n_members = len(MEMBER_NAMES)  # it answers whatever a method asks, as the ensemble would

    def __init__(self, walls: np.ndarray) -> None:
        walls = np.asarray(walls)
        if walls.ndim != 2 or walls.dtype != np.bool_:
            raise ValueError("the oracle needs the world's walls as a 2-D bool map")
        self.walls = walls

    def predict(
        self,
        observed: np.ndarray,
        region: Region | None = None,
        members: Sequence[int] | None = None,
    ) -> OraclePrediction:
        """The truth on the unknown cells of `region` (whole map if None), for every member
        asked (all if None)."""
        if observed.shape != self.walls.shape:
            raise ValueError(f"the oracle knows a {self.walls.shape} map, not {observed.shape}")
        members = tuple(range(self.n_members)) if members is None else tuple(members)
        return oracle_prediction(observed, self.walls, (0, 0), region, members)

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """The walls for each member, float32 (len(members), rows, cols): the oracle knows
        where only a whole map lies, so a crop must be the whole map (`predict` takes a
        region)."""
        if observed.shape != self.walls.shape:
            raise ValueError("the oracle predicts a region through `predict`, not a crop")
        return np.repeat(self.walls[None].astype(np.float32), len(members), axis=0)
