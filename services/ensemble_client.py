"""The planner's side of the predictor pool: an ensemble whose members answer over Zenoh.

`ZenohEnsemble` tracks the live workers of every member through their liveliness tokens and
sends each prediction's queries at once, each to the least recently used live worker of its
member. A member that does not answer is left out and the step recorded as degraded; a
worker that let a query time out is benched until a health probe says it is not stuck; each
request carries its budget (docs/design.md#following-one-scan,
docs/design.md#reliability). Its interface is that of every `Predictor`: `predict`,
`predict_later`, `wait` and `close`.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import zenoh

from mapex.prediction.base import (
    MEMBER_NAMES,
    EnsemblePrediction,
    Predictor,
    Region,
    assemble_prediction,
)
from mapex.prediction.config import NetworkConfig
from services.codec import DEFAULT_SERVICES, ProtocolError
from services.config import ServicesConfig
from services.keys import AliveKey, alive_predictor_pattern, health_key, parse_key, predict_key
from services.messages import ErrorReply, HealthReply, PredictReply, PredictRequest, decode_message

_WAIT_POLL_S = 0.02  # polling step of `wait`
_ZENOH_TIMEOUT = b"Timeout"  # the error payload Zenoh ends a timed-out query with

log = logging.getLogger("services.ensemble_client")


@dataclass(frozen=True)
class _Answers:
    """What the pool answered for one crop: float32 (len(answered), h, w) in the order of
    `answered` (member indices), and the worker that served each of them."""

    probabilities: np.ndarray
    answered: tuple[int, ...]
    workers: tuple[str, ...]

    def missing(self, members: Sequence[int]) -> tuple[int, ...]:
        return tuple(k for k in members if k not in self.answered)


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
        self._lock = threading.Lock()
        self._live: dict[str, dict[str, int]] = {name: {} for name in MEMBER_NAMES}  # -> last use
        self._benched: dict[tuple[str, str], float] = {}  # (member, worker) -> next probe time
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

    def benched_workers(self) -> dict[str, tuple[str, ...]]:
        """The workers of every member (sorted) that get no query until a probe clears them."""
        with self._lock:
            benched = sorted(self._benched)
        return {name: tuple(w for m, w in benched if m == name) for name in MEMBER_NAMES}

    def wait(
        self, timeout_s: float = 10.0, members: Sequence[str] = MEMBER_NAMES, count: int = 1
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
            self._benched.pop((parsed.member, parsed.worker_id), None)  # a new incarnation
        change = "joined" if alive else "left"
        log.info("worker %s of member %s %s", parsed.worker_id, parsed.member, change)

    def _choose_worker(self, member: str) -> str | None:
        """The least recently used live, unbenched worker of `member` (ties by id), now
        marked used; benched workers due for a health probe are probed first."""
        self._probe_benched(member)
        with self._lock:
            workers = {
                w: used
                for w, used in self._live[member].items()
                if (member, w) not in self._benched
            }
            if not workers:
                return None
            worker_id = min(workers, key=lambda w: (workers[w], w))
            self._live[member][worker_id] = next(self._ticks)
            return worker_id

    def _bench(self, member: str, worker_id: str) -> None:
        with self._lock:
            self._benched[(member, worker_id)] = (
                time.monotonic() + self.services.health_probe_every_s
            )
        log.warning(
            "member %s: worker %s benched after a timeout (no queries until it answers a "
            "health probe)", member, worker_id,
        )  # fmt: skip

    def _probe_benched(self, member: str) -> None:
        """Send a health probe to each benched worker of `member` whose probe is due."""
        now = time.monotonic()
        with self._lock:
            due = [w for (m, w), at in self._benched.items() if m == member and at <= now]
            for worker_id in due:
                self._benched[(member, worker_id)] = now + self.services.health_probe_every_s
        for worker_id in due:
            self.session.get(
                health_key(member, worker_id),
                self._on_probe_reply,
                timeout=self.services.health_probe_timeout_s,
            )

    def _on_probe_reply(self, reply: zenoh.Reply) -> None:
        """Un-bench a worker whose health reply says it is not stuck in a prediction."""
        if reply.ok is None:
            return
        try:
            health = HealthReply.decode(reply.ok.payload.to_bytes(), self.services)
        except ProtocolError as error:
            log.warning("ignored a health reply: %s", error)
            return
        if health.busy_s >= self.services.predict_timeout_s:
            return  # still stuck in one prediction
        with self._lock:
            back = self._benched.pop((health.member, health.worker_id), None) is not None
        if back:
            log.info("member %s: worker %s answered a health probe: back in use",
                     health.member, health.worker_id)  # fmt: skip

    # ------------------------------------------------------------------ prediction

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """Every requested member's probabilities for the crop `observed`, float32
        (len(members), h, w); RuntimeError naming the members that did not answer."""
        answers = self._finish(self._start(observed, members))
        missing = answers.missing(members)
        if missing:
            names = ", ".join(MEMBER_NAMES[k] for k in missing)
            raise RuntimeError(f"members {names} did not answer")
        return answers.probabilities

    def predict(
        self,
        observed: np.ndarray,
        region: Region | None = None,
        members: Sequence[int] | None = None,
    ) -> EnsemblePrediction:
        """`Predictor.predict` with only the members that answered (`member_ids` says which).

        Every member is asked at once; this waits at most `services.predict_timeout_s`. A query
        that ends with no reply at all (no queryable was routed: a worker just left, a link or a
        route was being re-established; Zenoh then ends a query at once with no reply,
        eclipse-zenoh/zenoh#2767) is sent again after a short pause, up to
        `services.predict_retries` times; a timed-out or refused one is not (a hung worker costs
        one timeout, docs/design.md#reliability). The main map is G's only if G answered
        (`member_ids[0] == 0`).
        """
        return self.predict_later(observed, region, members)()

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
        r0, r1, c0, c1 = self.members_window(observed.shape, region)
        inflight = self._start(observed[r0:r1, c0:c1], members)

        def result() -> EnsemblePrediction:
            answers = self._finish(inflight)
            return assemble_prediction(
                observed, region, answers.probabilities, answers.answered, self.context_cells,
                answers.workers,
            )  # fmt: skip

        return result

    def _start(self, crop: np.ndarray, members: Sequence[int]) -> _Inflight:
        """Send one query per member (none for an empty crop)."""
        members = tuple(members)
        if crop.size == 0:  # nothing to predict (PredictRequest needs a non-empty map)
            return _Inflight(-1, b"", crop.shape, members, [])
        request_id = next(self._request_ids)
        budget_s = self.services.predict_timeout_s
        payload = PredictRequest(request_id, crop, budget_s).encode(self.services)
        sent = [p for p in (self._send(k, payload) for k in members) if p is not None]
        return _Inflight(request_id, payload, crop.shape, members, sent)

    def _finish(self, inflight: _Inflight) -> _Answers:
        """Collect the replies (re-sending unrouted queries) and assemble the answers."""
        members, shape = inflight.members, inflight.shape
        if inflight.request_id < 0:
            empty = np.zeros((len(members), *shape), dtype=np.float32)
            return _Answers(empty, members, ("",) * len(members))
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
        return _Answers(stacked, answered, tuple(results[k].worker_id for k in answered))

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
        if any(_timed_out(reply) for reply in replies):
            self._bench(name, pending.worker_id)
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


def _timed_out(reply: zenoh.Reply) -> bool:
    """Whether `reply` is Zenoh's own end of a query that timed out."""
    return reply.err is not None and reply.err.payload.to_bytes() == _ZENOH_TIMEOUT


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
