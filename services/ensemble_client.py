"""The planner's side of the predictor pool: an ensemble whose members answer over Zenoh.

`ZenohEnsemble` tracks the live workers of every member through their liveliness tokens
(a query at start plus a subscriber for joins and leaves). A prediction sends one query per
member, all issued before any reply is awaited, each to the least recently used live worker
of that member: replicas share the load and every query is answered by exactly one worker.
A member whose worker times out, refuses, sends an invalid reply or has no live worker is
left out, and the result says which members answered: the planner goes on with those
(docs/design.md#reliability) and records the step as degraded.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import zenoh

from mapex.prediction.base import MEMBER_NAMES, EnsemblePrediction, Predictor, Region
from mapex.prediction.config import NetworkConfig
from services.codec import DEFAULT_SERVICES, ProtocolError
from services.config import ServicesConfig
from services.keys import AliveKey, alive_predictor_pattern, parse_key, predict_key
from services.messages import ErrorReply, PredictReply, PredictRequest, decode_message

_WAIT_POLL_S = 0.02  # polling step of `wait_for_workers`

log = logging.getLogger("services.ensemble_client")


class MembersMissingError(RuntimeError):
    """Some requested members did not answer (use `predict_available` to go on without them)."""


@dataclass(frozen=True)
class MemberAnswers:
    """What the pool answered for one crop.

    probabilities: float32 (len(answered), h, w), in the order of `answered` (member indices);
    missing: the requested members that did not answer; workers / compute_ms: per answered
    member, the worker that served it and its compute time in milliseconds.
    """

    probabilities: np.ndarray
    answered: tuple[int, ...]
    missing: tuple[int, ...]
    workers: dict[int, str] = field(default_factory=dict)
    compute_ms: dict[int, float] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        """Whether every requested member answered."""
        return not self.missing


@dataclass
class _Inflight:
    """One prediction whose queries are out: what `_finish` needs to collect them."""

    request_id: int  # -1: nothing was sent (empty crop)
    payload: bytes
    shape: tuple[int, ...]
    members: tuple[int, ...]
    pending: list[_Pending]


@dataclass
class _Pending:
    """One query in flight: member index, chosen worker, and the handler its replies reach."""

    member: int
    worker_id: str
    replies: zenoh.Handler


class ZenohEnsemble(Predictor):
    """The ensemble G, G_1..G_3 served by predictor workers reachable through `session`."""

    name = "zenoh"
    n_members = len(MEMBER_NAMES)
    context_cells = NetworkConfig().context_cells  # as the learned workers' own ensemble

    def __init__(self, session: zenoh.Session, services: ServicesConfig = DEFAULT_SERVICES) -> None:
        self.session = session
        self.services = services
        self.last_answers: MemberAnswers | None = None
        self._lock = threading.Lock()
        self._live: dict[str, dict[str, int]] = {name: {} for name in MEMBER_NAMES}  # -> last use
        self._ticks = itertools.count(1)
        self._request_ids = itertools.count()
        pattern = alive_predictor_pattern()
        self._subscriber = session.liveliness().declare_subscriber(
            pattern, self._on_liveliness, history=True
        )
        for reply in session.liveliness().get(pattern, timeout=services.liveliness_query_timeout_s):
            if reply.ok is not None:
                self._set_alive(str(reply.ok.key_expr), alive=True)

    # ------------------------------------------------------------------ worker discovery

    def live_workers(self) -> dict[str, tuple[str, ...]]:
        """The live worker ids of every member (sorted), as the liveliness tokens say now."""
        with self._lock:
            return {name: tuple(sorted(workers)) for name, workers in self._live.items()}

    def wait_for_workers(
        self, members: Sequence[str] = MEMBER_NAMES, timeout_s: float = 10.0, count: int = 1
    ) -> bool:
        """Wait until each of `members` has at least `count` live workers; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            live = self.live_workers()
            if all(len(live[name]) >= count for name in members):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(_WAIT_POLL_S)

    def close(self) -> None:
        """Stop tracking workers (the session stays open: it belongs to the caller)."""
        self._subscriber.undeclare()

    def __enter__(self) -> ZenohEnsemble:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        self._set_alive(str(sample.key_expr), alive=sample.kind == zenoh.SampleKind.PUT)

    def _set_alive(self, key: str, alive: bool) -> None:
        try:
            parsed = parse_key(key)
        except ProtocolError as error:
            log.warning("ignored a liveliness token: %s", error)
            return
        if not (isinstance(parsed, AliveKey) and parsed.role == "predict"):
            return
        with self._lock:
            workers = self._live[parsed.member]
            if alive:
                workers.setdefault(parsed.worker_id, 0)
            else:
                workers.pop(parsed.worker_id, None)
        change = "joined" if alive else "left"
        log.info("worker %s of member %s %s", parsed.worker_id, parsed.member, change)

    def _choose_worker(self, member: str) -> str | None:
        """The least recently used live worker of `member` (ties by id), now marked used."""
        with self._lock:
            workers = self._live[member]
            if not workers:
                return None
            worker_id = min(workers, key=lambda w: (workers[w], w))
            workers[worker_id] = next(self._ticks)
            return worker_id

    # ------------------------------------------------------------------ prediction

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """All requested members' probabilities, float32 (len(members), h, w).

        Raises MembersMissingError when one did not answer (`last_answers` says which).
        """
        answers = self.predict_available(observed, members)
        if answers.missing:
            names = ", ".join(MEMBER_NAMES[k] for k in answers.missing)
            raise MembersMissingError(f"members {names} did not answer")
        return answers.probabilities

    def predict(
        self,
        observed: np.ndarray,
        region: Region | None = None,
        members: Sequence[int] | None = None,
    ) -> EnsemblePrediction:
        """`Predictor.predict` with only the members that answered (`answered` says which)."""
        return self.predict_ensemble(observed, region, members)[0]

    def predict_available(self, observed: np.ndarray, members: Sequence[int]) -> MemberAnswers:
        """Ask every member in `members` for the crop `observed` in parallel; keep who answers.

        Waits at most `services.predict_timeout_s` (all queries run concurrently). A query
        that ends with no reply at all (no queryable was routed: a worker just left, a link
        or a route was being re-established: Zenoh then ends a query at once with no
        reply, eclipse-zenoh/zenoh#2767) is sent again after a short pause, up to
        `services.predict_retries` times; a timed-out or refused one is not (a hung worker
        costs one timeout, docs/design.md#reliability).
        """
        return self._finish(self._start(observed, members))

    def predict_later(
        self,
        observed: np.ndarray,
        region: Region | None = None,
        members: Sequence[int] | None = None,
    ) -> Callable[[], EnsemblePrediction]:
        """Send the queries now; the returned function waits for the answers (`predict`'s).

        The workers compute while the caller goes on (e.g. the metrics' whole-map G
        prediction overlaps the next steps of exploration). `observed` must not change.
        """
        members = tuple(range(self.n_members)) if members is None else tuple(members)
        inflight = self._start(self._members_view(observed, region), members)

        def result() -> EnsemblePrediction:
            answers = self._finish(inflight)
            return self._assemble(observed, region, answers)

        return result

    def _start(self, crop: np.ndarray, members: Sequence[int]) -> _Inflight:
        """Send one query per member (none for an empty crop)."""
        members = tuple(members)
        if crop.size == 0:  # nothing to predict (PredictRequest needs a non-empty map)
            return _Inflight(-1, b"", crop.shape, members, [])
        request_id = next(self._request_ids)
        payload = PredictRequest(request_id, crop).encode(self.services)
        sent = [p for p in (self._send(k, payload) for k in members) if p is not None]
        return _Inflight(request_id, payload, crop.shape, members, sent)

    def _finish(self, inflight: _Inflight) -> MemberAnswers:
        """Collect the replies (re-sending unrouted queries) and assemble the answers."""
        members, shape = inflight.members, inflight.shape
        if inflight.request_id < 0:
            empty = np.zeros((len(members), *shape), dtype=np.float32)
            self.last_answers = MemberAnswers(empty, members, ())
            return self.last_answers
        results: dict[int, PredictReply | None] = {}
        pending = inflight.pending
        for attempt in range(1 + self.services.predict_retries):
            collected = {p.member: self._collect(p, inflight.request_id, shape) for p in pending}
            results.update({k: reply for k, (reply, _) in collected.items()})
            unrouted = [k for k, (_, routed) in collected.items() if not routed]
            if not unrouted or attempt == self.services.predict_retries:
                break
            time.sleep(self.services.predict_retry_pause_s * 2**attempt)  # let routes settle
            sent = (self._send(k, inflight.payload) for k in unrouted)
            pending = [p for p in sent if p is not None]
        answered = tuple(k for k in members if results.get(k) is not None)
        stacked = np.empty((len(answered), *shape), dtype=np.float32)
        for row, k in enumerate(answered):
            stacked[row] = results[k].probabilities()
        answers = MemberAnswers(
            stacked,
            answered,
            tuple(k for k in members if k not in answered),
            {k: results[k].worker_id for k in answered},
            {k: results[k].compute_ms for k in answered},
        )
        self.last_answers = answers
        return answers

    def predict_ensemble(
        self,
        observed: np.ndarray,
        region: Region | None = None,
        members: Sequence[int] | None = None,
    ) -> tuple[EnsemblePrediction, MemberAnswers]:
        """Like `predict`, with only the members that answered (row i is `answered[i]`).

        The prediction's main map is member 0 only if G answered (check `answered[0] == 0`).
        """
        members = tuple(range(self.n_members)) if members is None else tuple(members)
        answers = self.predict_available(self._members_view(observed, region), members)
        return self._assemble(observed, region, answers), answers

    def _members_view(self, observed: np.ndarray, region: Region | None) -> np.ndarray:
        """The crop the workers predict (`Predictor.members_window`)."""
        r0, r1, c0, c1 = self.members_window(observed.shape, region)
        return observed[r0:r1, c0:c1]

    def _assemble(
        self, observed: np.ndarray, region: Region | None, answers: MemberAnswers
    ) -> EnsemblePrediction:
        answered = _Answered(answers.probabilities, self.context_cells)
        return answered.predict(observed, region, answers.answered)

    def _send(self, member: int, payload: bytes) -> _Pending | None:
        name = MEMBER_NAMES[member]
        worker_id = self._choose_worker(name)
        if worker_id is None:
            log.warning("member %s has no live worker", name)
            return None
        replies = self.session.get(
            predict_key(name, worker_id), payload=payload, timeout=self.services.predict_timeout_s
        )
        return _Pending(member, worker_id, replies)

    def _collect(
        self, pending: _Pending, request_id: int, shape: tuple[int, ...]
    ) -> tuple[PredictReply | None, bool]:
        """(the valid reply of one query or None (logged), whether any reply came at all)."""
        name, where = MEMBER_NAMES[pending.member], f"worker {pending.worker_id}"
        replies = list(pending.replies)  # ends when the query is finalised or times out
        if not replies:  # no queryable matched (the worker just left) or it sent nothing
            log.warning("member %s: %s sent no reply", name, where)
            return None, False
        for reply in replies:
            message, problem = self._check_reply(reply, request_id, name, shape)
            if problem is None:
                return message, True
            log.warning("member %s: %s gave no prediction: %s", name, where, problem)
        return None, True

    def _check_reply(
        self, reply: zenoh.Reply, request_id: int, member: str, shape: tuple[int, ...]
    ) -> tuple[PredictReply | None, str | None]:
        """(the reply's PredictReply, None) when it answers this query, else (None, why not)."""
        payload = (reply.ok or reply.err).payload.to_bytes()
        try:
            message = decode_message(payload, (PredictReply, ErrorReply), self.services)
        except ProtocolError as error:
            if reply.err is not None:  # Zenoh's own error, e.g. "Timeout"
                return None, " ".join(payload.decode("utf-8", "replace").split())
            return None, str(error)
        problem = _reply_problem(message, request_id, member, shape)
        return (message, None) if problem is None else (None, problem)


def _reply_problem(
    message: PredictReply | ErrorReply, request_id: int, member: str, shape: tuple[int, ...]
) -> str | None:
    """Why `message` is not the answer to this query, or None when it is."""
    if isinstance(message, ErrorReply):
        return f"error reply: {message.message}"
    if message.request_id != request_id:
        return f"reply to request {message.request_id}, expected {request_id}"
    if message.member != member:
        return f"reply from member {message.member}, expected {member}"
    if message.probabilities_u8.shape != tuple(shape):
        return f"reply of shape {message.probabilities_u8.shape}, expected {tuple(shape)}"
    return None


class _Answered(Predictor):
    """Already computed member outputs, so `Predictor.predict` can assemble them."""

    def __init__(self, probabilities: np.ndarray, context_cells: int) -> None:
        self.probabilities = probabilities
        self.n_members = len(probabilities)
        self.context_cells = context_cells

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        return self.probabilities
