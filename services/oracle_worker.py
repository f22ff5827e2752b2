"""The oracle's predictor worker: the ground truth of the run a request names, as member g's
answer (docs/design.md#the-oracle-worker).

`python -m services.predictor --predictor oracle --member g` serves it with no network and no
torch. A request names its run and its crop's top-left cell in that run's map
(`PredictRequest.run`, `.origin`); the worker asks for the run's ground truth once, on the
world's queryable `mapex/@v1/<run>/ground_truth` (a planner that simulates its world itself
serves it there too), and keeps the last few runs' walls: one pool serves many runs at once
(`services.evaluate`). A request without run and origin, or whose crop falls outside the
map or contradicts its known cells, or of a run nobody serves the ground truth of, is refused
with an error reply (kept walls that do not fit are fetched again first). What it answers is
checked cell by cell by the planner, which holds the run's ground truth itself.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

import numpy as np
import zenoh

from mapex.grid import FREE, OCCUPIED
from mapex.prediction.oracle import ORACLE
from services.codec import ProtocolError
from services.config import ServicesConfig
from services.keys import run_key
from services.messages import GroundTruth, PredictRequest

_RETRY_PAUSE_S = 0.2  # between queries for a ground truth nobody answered yet
_QUERY_TIMEOUT_S = 1.0  # one query for a ground truth

log = logging.getLogger("services.oracle_worker")

TruthSource = Callable[[str], np.ndarray | None]
"""run id -> its walls, bool (rows, cols), or None when nobody serves its ground truth."""


class RequestRefusedError(ValueError):
    """A request the worker will not answer; its one-line message goes back as the error."""


class GroundTruths:
    """The walls of the last `size` runs asked for, each fetched once through `fetch`."""

    def __init__(self, fetch: TruthSource, size: int) -> None:
        if size < 1:
            raise ValueError(f"size must be >= 1, not {size}")
        self.fetch = fetch
        self.size = size
        self._walls: OrderedDict[str, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def walls(self, run: str, fresh: bool = False) -> np.ndarray:
        """Run `run`'s walls (`fresh`: fetched again, not the kept ones); RequestRefusedError
        when nobody serves its ground truth (not kept: a later request asks again)."""
        with self._lock:
            if fresh:
                self._walls.pop(run, None)
            if run in self._walls:
                self._walls.move_to_end(run)
                return self._walls[run]
        walls = self.fetch(run)
        if walls is None:
            raise RequestRefusedError(
                f"no ground truth for run {run}: nothing answers {run_key(run, 'ground_truth')}"
            )
        with self._lock:
            self._walls[run] = walls
            while len(self._walls) > self.size:
                self._walls.popitem(last=False)
        return walls

    def runs(self) -> tuple[str, ...]:
        """The runs whose walls are kept, least recently used first."""
        with self._lock:
            return tuple(self._walls)


class OracleMember:
    """Member g of the oracle: the true walls of a request's crop, float32 (h, w) 0 / 1."""

    name = ORACLE

    def __init__(self, truths: GroundTruths) -> None:
        self.truths = truths

    def predict_request(self, request: PredictRequest) -> np.ndarray:
        """The walls under the crop of `request`; RequestRefusedError (one line) when it names no
        run and origin, or its crop falls outside the run's map or contradicts its known cells
        (a scan sees the truth). The kept walls of a run that do not fit are fetched again
        first: a later run may have taken the same id (a reused `services.up --run-prefix`)."""
        if request.run is None or request.origin is None:
            raise RequestRefusedError(
                "the oracle answers only a request naming its run and the crop's origin"
            )
        walls = self.truths.walls(request.run)
        if _misfit(walls, request) is not None:
            walls = self.truths.walls(request.run, fresh=True)
        if (problem := _misfit(walls, request)) is not None:
            raise RequestRefusedError(problem)
        (top, left), (rows, cols) = request.origin, request.observed.shape
        return walls[top : top + rows, left : left + cols].astype(np.float32)


def _misfit(walls: np.ndarray, request: PredictRequest) -> str | None:
    """Why the crop of `request` cannot be cut from `walls`, or None: it falls outside them,
    or a cell it knows is free or a wall where they say otherwise."""
    (top, left), (rows, cols) = request.origin, request.observed.shape
    if top + rows > walls.shape[0] or left + cols > walls.shape[1]:
        return (
            f"the {rows}x{cols} crop at {(top, left)} falls outside the "
            f"{walls.shape[0]}x{walls.shape[1]} map of run {request.run}"
        )
    truth, observed = walls[top : top + rows, left : left + cols], request.observed
    wrong = int(np.count_nonzero(((observed == FREE) & truth) | ((observed == OCCUPIED) & ~truth)))
    if wrong:
        return f"the crop contradicts the ground truth of run {request.run} on {wrong} known cells"
    return None


def zenoh_truth_source(session: zenoh.Session, services: ServicesConfig) -> TruthSource:
    """Fetch a run's walls on `session` from its ground-truth queryable, asking again until
    `services.oracle_truth_wait_s` has passed (its queryable may still be on its way); the
    first valid reply wins, malformed ones are logged and dropped."""

    def fetch(run: str) -> np.ndarray | None:
        key = run_key(run, "ground_truth")
        deadline = time.monotonic() + services.oracle_truth_wait_s
        while True:
            for reply in session.get(key, timeout=_QUERY_TIMEOUT_S):
                if reply.ok is None:
                    continue
                try:
                    truth = GroundTruth.decode(reply.ok.payload.to_bytes(), services)
                except ProtocolError as error:
                    log.warning("%s: dropped a reply: %s", key, error)
                    continue
                log.info("read the ground truth of run %s %s", run, truth.occupancy.shape)
                return truth.occupancy.copy()
            if time.monotonic() + _RETRY_PAUSE_S >= deadline:
                return None
            time.sleep(_RETRY_PAUSE_S)

    return fetch
