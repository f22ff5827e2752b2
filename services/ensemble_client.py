"""The planner's side of the predictor pool: an ensemble whose members answer over Zenoh.

`ZenohEnsemble` tracks the live workers of every member through their liveliness tokens and
sends each prediction's queries at once, each to the least recently used live worker of its
member. A member that does not answer, or whose answer is refused (it names another worker
than the one asked, or contradicts the known cells it was given), is left out and the step
recorded as degraded. The planner trusts what it measured over what a worker says: a worker
that failed is benched for a time that doubles with each further failure, and only a timely,
valid answer clears it, never its own health reply; each request carries its budget
(docs/design.md#following-one-scan, docs/design.md#reliability). Its interface is that of
every `Predictor`: `predict`, `predict_later`, `wait` and `close`.

It asks for the predictor the run was started with (`lama` by default, `lama-v2`, or
`oracle`): under the oracle it asks member g's oracle worker for the ground truth of the
region, naming the run and the crop's origin, checks the answer cell by cell against the
run's ground truth (which the planner holds for the metrics) and builds the
`OraclePrediction` every member's rows come from (docs/design.md#the-oracle-worker).
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

from mapex.grid import FREE, OCCUPIED, UNKNOWN, Cell, dequantise_probability, quantise_probability
from mapex.prediction import DEFAULT_PREDICTOR
from mapex.prediction.base import (
    MEMBER_NAMES,
    EnsemblePrediction,
    Predictor,
    Region,
    assemble_prediction,
)
from mapex.prediction.config import NetworkConfig
from mapex.prediction.oracle import ORACLE, oracle_prediction
from services.codec import DEFAULT_SERVICES, ProtocolError
from services.config import ServicesConfig
from services.keys import AliveKey, alive_predictor_pattern, health_key, parse_key, predict_key
from services.messages import (
    ErrorReply,
    HealthReply,
    PredictReply,
    PredictRequest,
    decode_message,
    map_message_bytes,
)

_WAIT_POLL_S = 0.02  # polling step of `wait`
_ZENOH_TIMEOUT = b"Timeout"  # the error payload Zenoh ends a timed-out query with
_MAX_DOUBLINGS = 30  # of a bench time (bench_max_s caps it long before)
# the lowest uint8 level of a reply that predicts "occupied" (probability >= 0.5)
_OCCUPIED_LEVEL = int(np.argmax(dequantise_probability(np.arange(256, dtype=np.uint8)) >= 0.5))

log = logging.getLogger("services.ensemble_client")


@dataclass(frozen=True)
class _Answers:
    """What the pool answered for one crop: float32 (len(answered), h, w) in the order of
    `answered` (member indices), and the worker queried for each of them."""

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
    crop: np.ndarray  # the observed crop asked about (answers are checked against it)
    members: tuple[int, ...]
    pending: list[_Pending]
    origin: Cell = (0, 0)  # the crop's top-left cell in the run's map


@dataclass
class _Pending:
    """One query in flight: member index, chosen worker, and the handler its replies reach."""

    member: int
    worker_id: str
    replies: zenoh.Handler


@dataclass
class _Standing:
    """What the planner measured of one worker (never what the worker says of itself)."""

    strikes: int = 0  # failed queries since its last good answer
    unanswered: int = 0  # of those, queries it ended with no reply at all, in a row
    benches: int = 0  # benches since its last good answer (each twice as long as the last)
    benched_until: float = 0.0  # monotonic time before which it gets no query
    next_probe: float = 0.0  # monotonic time of its next health probe while benched
    lied: bool = False  # its last failure was an answer refused (not a timeout or no reply)


class ZenohEnsemble(Predictor):
    """The ensemble G, G_1..G_3 of `predictor` served by predictor workers reachable through
    `session`; its `name` is the predictor's, as a run records it. The oracle needs the `run`
    (its workers read that run's ground truth) and the run's `walls` (its answers are checked
    against them)."""

    n_members = len(MEMBER_NAMES)
    context_cells = NetworkConfig().context_cells  # as the learned workers' own ensemble

    def __init__(
        self,
        session: zenoh.Session,
        services: ServicesConfig = DEFAULT_SERVICES,
        predictor: str = DEFAULT_PREDICTOR,
        run: str | None = None,
        walls: np.ndarray | None = None,
    ) -> None:
        self.oracle = predictor == ORACLE
        if self.oracle and (run is None or walls is None):
            raise ValueError("the oracle ensemble needs its run and the run's walls")
        self.name = predictor
        self.run = run
        self.walls = None if walls is None else np.asarray(walls, dtype=bool)
        # the members whose workers it asks: the oracle's one worker answers for all
        self.served_members = MEMBER_NAMES[:1] if self.oracle else MEMBER_NAMES
        if self.oracle:
            self.context_cells = 0  # the truth needs no map around the region
        self.session = session
        self.services = services
        self._lock = threading.Lock()
        self._live: dict[str, dict[str, int]] = {name: {} for name in MEMBER_NAMES}  # -> last use
        self._standing: dict[tuple[str, str], _Standing] = {}  # (member, worker) -> record
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
        """The workers of every member (sorted) that get no query now (benched)."""
        now = time.monotonic()
        with self._lock:
            benched = sorted(key for key, s in self._standing.items() if s.benched_until > now)
        return {name: tuple(w for m, w in benched if m == name) for name in MEMBER_NAMES}

    def wait(
        self, timeout_s: float = 10.0, members: Sequence[str] | None = None, count: int = 1
    ) -> bool:
        """Wait until each of `members` (default: those it asks, `served_members`) has at
        least `count` live workers; False on timeout."""
        members = self.served_members if members is None else members
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
        key = (parsed.member, parsed.worker_id)
        with self._lock:
            workers = self._live[parsed.member]
            new = alive and parsed.worker_id not in workers
            if alive:
                workers.setdefault(parsed.worker_id, 0)
            else:
                workers.pop(parsed.worker_id, None)
            standing = self._standing.get(key)
            if standing is not None and not alive and standing.strikes == 0:
                del self._standing[key]  # nothing against it left to remember
            elif standing is not None and new and not standing.lied and standing.benches <= 1:
                # a new incarnation (restarted by its supervisor after a hang) ends its first
                # bench; its strikes stay: failing again benches it for twice as long. A
                # worker benched for a refused answer, or benched again, waits its bench out
                # whatever tokens it declares
                standing.benched_until = 0.0
        if alive and not new:
            return  # a token seen twice (history and start-up query)
        change = "joined" if alive else "left"
        log.info("worker %s of member %s %s", parsed.worker_id, parsed.member, change)

    def _choose_worker(self, member: str) -> str | None:
        """The least recently used live, unbenched worker of `member` (ties by id), now
        marked used; benched workers due for a health probe are probed first."""
        self._probe_benched(member)
        now = time.monotonic()
        with self._lock:
            workers = {
                w: used
                for w, used in self._live[member].items()
                if not self._is_benched(member, w, now)
            }
            if not workers:
                return None
            worker_id = min(workers, key=lambda w: (workers[w], w))
            self._live[member][worker_id] = next(self._ticks)
            return worker_id

    def _is_benched(self, member: str, worker_id: str, now: float) -> bool:
        standing = self._standing.get((member, worker_id))
        return standing is not None and standing.benched_until > now

    def _succeeded(self, member: str, worker_id: str) -> None:
        """A timely, valid answer: the worker's record is clean again."""
        with self._lock:
            standing = self._standing.pop((member, worker_id), None)
        if standing is not None and standing.benches:
            log.info("member %s: worker %s answered in time again: its record is cleared",
                     member, worker_id)  # fmt: skip

    def _failed(
        self, member: str, worker_id: str, why: str, unanswered: bool = False, lied: bool = False
    ) -> None:
        """A failed query (`unanswered`: it ended with no reply at all; `lied`: its answer was
        refused): a strike, and a bench of `bench_first_s` doubled per earlier bench since its
        last good answer. Queries ending unanswered bench only the
        `bench_after_unanswered`-th in a row (a route may be still building); every other
        failure benches at once."""
        services = self.services
        now = time.monotonic()
        with self._lock:
            standing = self._standing.setdefault((member, worker_id), _Standing())
            standing.strikes += 1
            standing.lied = lied
            standing.unanswered = standing.unanswered + 1 if unanswered else 0
            if unanswered and standing.unanswered < services.bench_after_unanswered:
                return
            doubling = 2 ** min(standing.benches, _MAX_DOUBLINGS)
            bench_s = min(services.bench_first_s * doubling, services.bench_max_s)
            standing.benches += 1
            standing.benched_until = max(standing.benched_until, now + bench_s)
            standing.next_probe = now + services.health_probe_every_s
            strikes = standing.strikes
        log.warning(
            "member %s: worker %s benched for %g s (%s; %d failed queries since its last "
            "good answer)", member, worker_id, bench_s, why, strikes,
        )  # fmt: skip

    def _probe_benched(self, member: str) -> None:
        """Send a health probe to each benched worker of `member` whose probe is due. A probe
        can only keep a worker benched (it says it is stuck), never bring it back."""
        now = time.monotonic()
        with self._lock:
            due = [
                w
                for (m, w), s in self._standing.items()
                if m == member and s.benched_until > now and s.next_probe <= now
            ]
            for worker_id in due:
                self._standing[(member, worker_id)].next_probe = (
                    now + self.services.health_probe_every_s
                )
        for worker_id in due:
            self.session.get(
                health_key(member, worker_id),
                self._on_probe_reply(member, worker_id),
                timeout=self.services.health_probe_timeout_s,
            )

    def _on_probe_reply(self, member: str, worker_id: str) -> Callable[[zenoh.Reply], None]:
        """The handler of a probe sent to `member`'s `worker_id`: a worker that says it is still
        busy on one prediction past the timeout stays benched until the next probe can tell."""

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            try:
                health = HealthReply.decode(reply.ok.payload.to_bytes(), self.services)
            except ProtocolError as error:
                log.warning("ignored a health reply: %s", error)
                return
            if (health.member, health.worker_id) != (member, worker_id):
                log.warning("ignored a health reply of %s/%s to a probe of %s/%s",
                            health.member, health.worker_id, member, worker_id)  # fmt: skip
                return
            if health.busy_s < self.services.predict_timeout_s:
                return  # "idle" is its word: only a timely answer clears it
            probing = self.services.health_probe_every_s + self.services.health_probe_timeout_s
            hold = time.monotonic() + probing
            with self._lock:
                standing = self._standing.get((member, worker_id))
                if standing is not None and standing.benched_until > 0:
                    standing.benched_until = max(standing.benched_until, hold)

        return on_reply

    # ------------------------------------------------------------------ prediction

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """Every requested member's probabilities for the crop `observed`, float32
        (len(members), h, w); RuntimeError naming the members that did not answer (and under
        the oracle, which must know where a crop lies: use `predict`)."""
        if self.oracle:
            raise RuntimeError("the oracle predicts a region of the run's map: use predict")
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
        one timeout, docs/design.md#reliability). A reply is refused when it names another
        worker than the one asked or contradicts the known cells of the crop (`implausibility`);
        `workers` names the worker each answer was asked of. The main map is G's only if G
        answered (`member_ids[0] == 0`). Under the oracle the answer is an `OraclePrediction`
        of every member asked, or, when its worker did not answer, one of no member.
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
        asked = (0,) if self.oracle else members  # the oracle's worker serves g
        inflight = self._start(observed[r0:r1, c0:c1], asked, (r0, c0))

        def result() -> EnsemblePrediction:
            answers = self._finish(inflight)
            if self.oracle and answers.answered:
                truth, worker = answers.probabilities[0], answers.workers[0]
                return oracle_prediction(observed, truth, (r0, c0), region, members, worker)
            return assemble_prediction(
                observed, region, answers.probabilities, answers.answered, self.context_cells,
                answers.workers,
            )  # fmt: skip

        return result

    def _start(self, crop: np.ndarray, members: Sequence[int], origin: Cell = (0, 0)) -> _Inflight:
        """Send one query per member (none for an empty crop); `origin`: the crop's top-left
        cell in the run's map (sent under the oracle)."""
        members = tuple(members)
        if crop.size == 0:  # nothing to predict (PredictRequest needs a non-empty map)
            return _Inflight(-1, b"", crop, members, [], origin)
        request_id = next(self._request_ids)
        request = PredictRequest(
            request_id, crop, self.services.predict_timeout_s,
            self.run if self.oracle else None, origin if self.oracle else None,
            None if self.name == DEFAULT_PREDICTOR else self.name,
        )  # fmt: skip
        payload = request.encode(self.services)
        sent = [p for p in (self._send(k, payload) for k in members) if p is not None]
        return _Inflight(request_id, payload, crop.copy(), members, sent, origin)

    def _finish(self, inflight: _Inflight) -> _Answers:
        """Collect the replies (re-sending unrouted queries) and assemble the answers."""
        members, shape = inflight.members, inflight.crop.shape
        if inflight.request_id < 0:
            empty = np.zeros((len(members), *shape), dtype=np.float32)
            return _Answers(empty, members, ("",) * len(members))
        results: dict[int, tuple[PredictReply, str]] = {}  # member -> (reply, worker queried)
        pending = inflight.pending
        unanswered: set[str] = set()  # workers already struck for no reply to this request
        for attempt in range(1 + self.services.predict_retries):
            unrouted = []
            for each in pending:
                reply, routed = self._collect(each, inflight, unanswered)
                if reply is not None:
                    results[each.member] = (reply, each.worker_id)
                if not routed:
                    unrouted.append(each.member)
            if not unrouted or attempt == self.services.predict_retries:
                break
            time.sleep(self.services.predict_retry_pause_s * 2**attempt)  # let routes settle
            sent = (self._send(k, inflight.payload) for k in unrouted)
            pending = [p for p in sent if p is not None]
        answered = tuple(k for k in members if k in results)
        stacked = np.empty((len(answered), *shape), dtype=np.float32)
        for row, k in enumerate(answered):
            stacked[row] = results[k][0].probabilities()
        kept = self._agreeing(inflight.crop, stacked, answered, results)
        for k in kept:
            self._succeeded(MEMBER_NAMES[k], results[k][1])
        rows = [answered.index(k) for k in kept]
        return _Answers(stacked[rows], kept, tuple(results[k][1] for k in kept))

    def _agreeing(
        self,
        crop: np.ndarray,
        stacked: np.ndarray,
        answered: tuple[int, ...],
        results: dict[int, tuple[PredictReply, str]],
    ) -> tuple[int, ...]:
        """The members of `answered` whose answers do not dissent from the others' consensus
        (`dissent` above `consensus_max_disagreement`); each one that does is a failure of
        its worker (benched), left out as a missing member."""
        limit = self.services.consensus_max_disagreement
        if self.oracle or limit >= 1:
            return answered
        kept = []
        for k, share in zip(answered, dissent(crop, stacked, self.services), strict=True):
            if share is None or share <= limit:
                kept.append(k)
                continue
            why = f"its answer dissents on {share:.0%} of the cells the other members agree on"
            log.warning("member %s: worker %s: %s", MEMBER_NAMES[k], results[k][1], why)
            self._failed(MEMBER_NAMES[k], results[k][1], why, lied=True)
        return tuple(kept)

    def _send(self, member: int, payload: bytes) -> _Pending | None:
        name = MEMBER_NAMES[member]
        worker_id = self._choose_worker(name)
        if worker_id is None:
            log.warning("member %s has no live worker", name)
            return None
        replies = self.session.get(
            predict_key(name, worker_id), payload=payload, timeout=self.services.predict_timeout_s,
            consolidation=zenoh.ConsolidationMode.NONE,  # every reply, even two on one key
        )  # fmt: skip
        return _Pending(member, worker_id, replies)

    def _collect(
        self, pending: _Pending, inflight: _Inflight, unanswered: set[str]
    ) -> tuple[PredictReply | None, bool]:
        """(the valid reply of one query or None (logged), whether any reply came at all);
        the worker's record notes how it did (`unanswered`: the workers already struck for
        leaving this request unanswered, struck once per request)."""
        name, worker_id = MEMBER_NAMES[pending.member], pending.worker_id
        replies = list(pending.replies)  # ends when the query is finalised or times out
        if not replies:  # no queryable matched (the worker just left) or it sent nothing
            log.warning("member %s: worker %s sent no reply", name, worker_id)
            if worker_id not in unanswered:
                unanswered.add(worker_id)
                self._failed(name, worker_id, "no reply", unanswered=True)
            return None, False
        problem, valid = "no reply", []
        for reply in replies:
            message, problem = self._check_reply(reply, inflight, name, worker_id)
            if problem is None:
                valid.append(message)
            else:
                log.warning("member %s: worker %s gave no prediction: %s", name, worker_id, problem)
        if _different(valid):
            log.warning(
                "member %s: %d different answers on worker %s's key: another session answers "
                "as it; none is used", name, len(valid), worker_id,
            )  # fmt: skip
            return None, True
        if valid:
            return valid[0], True  # its record is cleared once the answers agree (_finish)
        timed_out = any(_timed_out(reply) for reply in replies)
        problem = "a timeout" if timed_out else problem
        lied = not timed_out and not problem.startswith(("error reply", "no reply"))
        self._failed(name, worker_id, problem, lied=lied)
        return None, True

    def _check_reply(
        self, reply: zenoh.Reply, inflight: _Inflight, member: str, worker_id: str
    ) -> tuple[PredictReply | None, str | None]:
        """(the reply's PredictReply, None) when it answers this query, sent to `worker_id`
        of `member`, plausibly; else (None, why not)."""
        payload = (reply.ok or reply.err).payload.to_bytes()
        try:
            limit = map_message_bytes(inflight.crop.size)  # one map of the crop
            message = decode_message(payload, (PredictReply, ErrorReply), self.services, limit)
        except ProtocolError as error:
            if reply.err is not None:  # Zenoh's own error, e.g. "Timeout"
                return None, " ".join(payload.decode("utf-8", "replace").split())
            return None, str(error)
        problem = _reply_problem(message, inflight.request_id, member, worker_id, inflight.crop)
        if problem is None and self.oracle:
            problem = self._untruth(inflight, message.probabilities_u8)
        elif problem is None:
            problem = implausibility(inflight.crop, message.probabilities_u8, self.services)
            if problem is not None:
                problem = f"implausible answer: {problem}"
        return (message, None) if problem is None else (None, problem)

    def _untruth(self, inflight: _Inflight, quantised: np.ndarray) -> str | None:
        """How an oracle answer for the crop of `inflight` differs from the run's ground
        truth, or None when it is the truth exactly (the `implausibility` rules are not
        applied: an honest crop whose unknown cells are all free is one value on them)."""
        (top, left), (rows, cols) = inflight.origin, inflight.crop.shape
        truth = quantise_probability(self.walls[top : top + rows, left : left + cols])
        if truth.shape != quantised.shape:
            return f"an oracle answer for a crop outside the {self.walls.shape} map"
        wrong = int(np.count_nonzero(quantised != truth))
        return None if wrong == 0 else f"wrong oracle answer: {wrong} cells are not the truth"


def _different(answers: list[PredictReply]) -> bool:
    """Whether `answers` to one query hold two different maps."""
    first = answers[0].probabilities_u8 if answers else None
    return any(not np.array_equal(a.probabilities_u8, first) for a in answers[1:])


def _timed_out(reply: zenoh.Reply) -> bool:
    """Whether `reply` is Zenoh's own end of a query that timed out."""
    return reply.err is not None and reply.err.payload.to_bytes() == _ZENOH_TIMEOUT


def _reply_problem(
    message: PredictReply | ErrorReply,
    request_id: int,
    member: str,
    worker_id: str,
    crop: np.ndarray,
) -> str | None:
    """Why `message` is not the answer to this query (sent to `worker_id` of `member`), or
    None when it is."""
    if isinstance(message, ErrorReply):
        return f"error reply: {message.message}"
    if message.request_id != request_id:
        return f"reply to request {message.request_id}, expected {request_id}"
    if message.member != member:
        return f"reply from member {message.member}, expected {member}"
    if message.worker_id != worker_id:
        return f"reply signed by worker {message.worker_id!r}, but {worker_id!r} was asked"
    if message.probabilities_u8.shape != crop.shape:
        return f"reply of shape {message.probabilities_u8.shape}, expected {crop.shape}"
    return None


def implausibility(
    crop: np.ndarray, quantised: np.ndarray, services: ServicesConfig = DEFAULT_SERVICES
) -> str | None:
    """Why the uint8 answer `quantised` to the observed `crop` cannot be a member's honest
    prediction, or None. A network sees the known cells of its crop: an answer that predicts
    occupied on more than `services.implausible_share` of the known free cells, or free on
    more than that share of the known walls (each judged from `implausible_min_cells` such
    cells), or one value on every unknown cell, contradicts its input (an all-free, all-wall,
    constant or inverted map). The shipped ensemble stays far below the share (its raw
    outputs are what this judges; known cells are copied through afterwards anyway)."""
    share, least = services.implausible_share, services.implausible_min_cells
    if share >= 1:
        return None  # the check is off
    occupied = quantised >= _OCCUPIED_LEVEL
    for code, wrong, what in (
        (FREE, occupied, "known free cells predicted occupied"),
        (OCCUPIED, ~occupied, "known walls predicted free"),
    ):
        known = crop == code
        count = int(np.count_nonzero(known))
        if count >= least:
            contradicted = int(np.count_nonzero(wrong & known))
            if contradicted > share * count:
                return f"{contradicted} of {count} {what}"
    unknown = quantised[crop == UNKNOWN]
    if unknown.size >= least and unknown.min() == unknown.max():
        return f"one value ({int(unknown[0])}/255) on all {unknown.size} unknown cells"
    return None


def dissent(
    crop: np.ndarray, answers: np.ndarray, services: ServicesConfig = DEFAULT_SERVICES
) -> list[float | None]:
    """For each of the member answers `answers` (k, h, w probabilities) to the observed
    `crop`: the share of the unknown cells where every *other* answer agrees (all walls or
    all free) on which it says the opposite, or None where that cannot be judged (fewer
    than three answers, or fewer than `implausible_min_cells` such cells). Honest members
    trained on the same data agree where they are sure; a forged answer that copies the
    known cells and invents the unknown ones does not."""
    walls = answers >= 0.5
    unknown = crop == UNKNOWN
    shares: list[float | None] = []
    for k in range(len(answers)):
        others = np.delete(walls, k, axis=0)
        if len(others) < 2:
            shares.append(None)
            continue
        all_walls, all_free = others.all(axis=0), ~others.any(axis=0)
        agreed = unknown & (all_walls | all_free)
        count = int(np.count_nonzero(agreed))
        if count < services.implausible_min_cells:
            shares.append(None)
            continue
        opposite = agreed & (walls[k] != all_walls)
        shares.append(np.count_nonzero(opposite) / count)
    return shares
