"""Predictor workers as real processes on loopback, and the planner's ZenohEnsemble client.

The test process opens the hub session on a free loopback port; workers are spawned with
subprocess (never forked) against it, with tiny random-weight networks, and are all killed
at teardown whatever happens.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
from service_processes import (
    REPO_ROOT,
    STOP_DEADLINE_S,
    ServiceProcesses,
    free_loopback_port,
    until,
)
from tiny_training import SMALL

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.prediction.base import MEMBER_NAMES, Predictor
from mapex.prediction.learned import LearnedEnsemble
from mapex.prediction.network import LamaGenerator
from mapex.prediction.weights import save_weights
from services.codec import DEFAULT_SERVICES, encode_array, pack_message
from services.config import ServicesConfig
from services.ensemble_client import ZenohEnsemble
from services.keys import alive_predictor_key, predict_key
from services.messages import ErrorReply, HealthReply, PredictReply, PredictRequest, decode_message
from services.predictor import MemberServer, serve
from services.zenoh_config import open_session, zenoh_config

# random-weight networks contradict the known cells of their crops: no plausibility check
# (services/ensemble_client.py `implausibility`; tests/services/test_rogue_workers.py)
UNCHECKED = {"implausible_share": 1.0, "consensus_max_disagreement": 1.0}  # random weights
FAST = ServicesConfig(predict_timeout_s=3.0, liveliness_query_timeout_s=1.0, **UNCHECKED)
START_DEADLINE_S = 60.0  # six workers import torch at once on a shared 2-core machine
QUANTUM = 1 / 255  # uint8 replies, plus float noise between processes
STOP_SLACK_S = 1.5  # a stopping worker: signal, undeclare, close its session, exit
# member -> worker ids started for the module: a replica of g, and a g2 worker to stop
WORKERS = {"g": ("g-a", "g-b"), "g1": ("g1-a",), "g2": ("g2-a", "g2-stop"), "g3": ("g3-a",)}


def partly_observed(shape=(64, 96), seed=0) -> np.ndarray:
    """A room seen from inside plus scattered known cells, the rest unknown."""
    observed = np.full(shape, UNKNOWN, dtype=np.uint8)
    observed[8:40, 10:60] = FREE
    observed[7, 9:61] = OCCUPIED
    observed[8:40, 9] = OCCUPIED
    rng = np.random.default_rng(seed)
    scattered = rng.random(shape) < 0.05
    observed[scattered] = rng.choice([FREE, OCCUPIED], scattered.sum())
    return observed


class WorkerPool(ServiceProcesses):
    """Predictor worker processes spawned against one hub."""

    def __init__(self, hub_endpoint: str, weights_dir: Path, log_dir: Path) -> None:
        super().__init__(hub_endpoint, log_dir)
        self.weights_dir = weights_dir

    def start(self, member: str, worker_id: str, *flags: str):
        return self.spawn(
            worker_id, "services.predictor", "--member", member, "--worker-id", worker_id,
            "--weights-dir", str(self.weights_dir), *flags,
        )  # fmt: skip

    def wait_alive(self, ensemble: ZenohEnsemble, member: str, worker_id: str) -> None:
        announced = lambda: worker_id in ensemble.live_workers()[member]  # noqa: E731
        self.wait_until_announced(worker_id, announced, START_DEADLINE_S)


@pytest.fixture(scope="module")
def weights_dir(tmp_path_factory) -> Path:
    directory = tmp_path_factory.mktemp("weights")
    for index, name in enumerate(MEMBER_NAMES):
        torch.manual_seed(index)
        save_weights(directory / f"{name}.pt", LamaGenerator(SMALL), {"member": name})
    return directory


@pytest.fixture(scope="module")
def pool(hub, weights_dir, tmp_path_factory):
    workers = WorkerPool(hub[1], weights_dir, tmp_path_factory.mktemp("logs"))
    try:
        for member, worker_ids in WORKERS.items():
            for worker_id in worker_ids:
                workers.start(member, worker_id)
        yield workers
    finally:
        workers.kill_all()


@pytest.fixture(scope="module")
def ensemble(hub, pool):
    client = ZenohEnsemble(hub[0], FAST)
    try:
        for member, worker_ids in WORKERS.items():
            for worker_id in worker_ids:
                pool.wait_alive(client, member, worker_id)
        yield client
    finally:
        client.close()


class RecordingSession:
    """A session stand-in that keeps every reply of every get (gets run one after another)."""

    def __init__(self, session) -> None:
        self.session = session
        self.gets: list[tuple[str, list]] = []

    def liveliness(self):
        return self.session.liveliness()

    def get(self, key, **options):
        replies = list(self.session.get(key, **options))
        self.gets.append((str(key), replies))
        return iter(replies)


class UnroutedSession(RecordingSession):
    """A session stand-in whose first `unrouted` gets end at once with no reply, as Zenoh's
    do while a route to the queryable is being built."""

    def __init__(self, session, unrouted: int) -> None:
        super().__init__(session)
        self.unrouted = unrouted

    def get(self, key, **options):
        if len(self.gets) < self.unrouted:
            self.gets.append((str(key), []))
            return iter(())
        return super().get(key, **options)


# ---------------------------------------------------------------------- real worker processes


def test_predictions_match_the_in_process_ensemble(ensemble, weights_dir):
    observed = partly_observed()
    local = LearnedEnsemble(weights_dir).predict(observed)
    remote = ensemble.predict(observed)
    np.testing.assert_allclose(remote.members, local.members, atol=QUANTUM + 1e-6)
    assert remote.member_ids == (0, 1, 2, 3) and len(remote.workers) == 4
    region = (4, 50, 0, 70)
    prediction = ensemble.predict(observed, region, members=(1, 2, 3))
    assert prediction.member_ids == (1, 2, 3)
    local_region = LearnedEnsemble(weights_dir).predict(observed, region, members=(1, 2, 3))
    np.testing.assert_allclose(prediction.members, local_region.members, atol=QUANTUM + 1e-6)


def test_replicas_share_queries_and_answer_each_exactly_once(hub, ensemble):
    recording = RecordingSession(hub[0])
    client = ZenohEnsemble(recording, FAST)
    try:
        assert client.wait(members=("g",), count=2)
        crop = partly_observed((40, 40), seed=1)
        served = [client.predict(crop, members=(0,)).workers[0] for _ in range(8)]
    finally:
        client.close()
    assert set(served) == {"g-a", "g-b"}
    assert served.count("g-a") == served.count("g-b") == 4  # least recently used alternates
    assert len(recording.gets) == 8
    for key, replies in recording.gets:
        assert len(replies) == 1 and replies[0].ok is not None
        reply = PredictReply.decode(replies[0].ok.payload.to_bytes())
        assert key == predict_key("g", reply.worker_id)


def _malformed_payloads() -> dict[str, bytes]:
    wrong_dtype = {"request_id": 1, "observed": encode_array(np.zeros((4, 4), np.float32))}
    bad_codes = {"request_id": 1, "observed": encode_array(np.full((4, 4), 7, np.uint8))}
    return {
        "random bytes": np.random.default_rng(3).bytes(200),
        "wrong schema": msgpack.packb({"schema": 99, "type": "predict_request"}),
        "wrong type": ErrorReply("not a request").encode(),
        "wrong dtype": pack_message("predict_request", wrong_dtype),
        "bad codes": pack_message("predict_request", bad_codes),
    }


def test_malformed_requests_get_an_error_reply_and_the_worker_lives_on(hub, pool, ensemble):
    session, key = hub[0], predict_key("g1", "g1-a")
    for what, payload in _malformed_payloads().items():
        replies = list(session.get(key, payload=payload, timeout=FAST.predict_timeout_s))
        assert len(replies) == 1 and replies[0].err is not None, what
        error = decode_message(replies[0].err.payload.to_bytes(), (ErrorReply,))
        assert error.message.startswith("malformed predict request"), what
    assert pool.processes["g1-a"].poll() is None
    assert ensemble.predict(partly_observed(), members=(1,)).member_ids == (1,)
    assert "refused a malformed request" in pool.log_of("g1-a")


def test_a_killed_worker_is_reported_missing_and_the_others_answer(hub, pool, ensemble):
    pool.processes["g3-a"].send_signal(signal.SIGKILL)
    pool.processes["g3-a"].wait(STOP_DEADLINE_S)
    try:
        started = time.monotonic()
        answers = ensemble.predict(partly_observed(), members=(0, 1, 2, 3))
        assert time.monotonic() - started < FAST.predict_timeout_s + 2.0
        assert answers.member_ids == (0, 1, 2)
        assert answers.members.shape == (3, *partly_observed().shape)
        with pytest.raises(RuntimeError, match="g3"):
            ensemble.predict_members(partly_observed(), (2, 3))
        until(lambda: not ensemble.live_workers()["g3"], "the token of the killed worker to go")
    finally:  # a supervisor would restart it; so do we, for the other tests
        pool.start("g3", "g3-b")
        pool.wait_alive(ensemble, "g3", "g3-b")
    assert ensemble.predict(partly_observed(), members=(3,)).workers == ("g3-b",)


def test_sigint_stops_a_worker_cleanly(pool, ensemble):
    process = pool.processes["g2-stop"]
    process.send_signal(signal.SIGINT)
    assert process.wait(STOP_DEADLINE_S) == 0
    until(lambda: "g2-stop" not in ensemble.live_workers()["g2"], "the token to be undeclared")
    log = pool.log_of("g2-stop")
    assert "stopped after answering" in log and "Traceback" not in log


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--member", "g", "--weights-dir", "{missing}"], "no weights file"),
        (["--member", "g", "--worker-id", "Bad Id"], "'Bad Id' must match"),
        (["--member", "g", "--listen", "tcp/127.0.0.1:99999"], "cannot open a Zenoh session"),
        (["--member", "g", "--precision", "float16"], "invalid choice: 'float16'"),
    ],
)
def test_bad_flags_and_missing_weights_are_one_line_errors(flags, message, tmp_path, weights_dir):
    flags = [f.format(missing=tmp_path / "none") for f in flags]
    if "--weights-dir" not in flags:
        flags += ["--weights-dir", str(weights_dir)]
    result = subprocess.run(
        [sys.executable, "-m", "services.predictor", *flags],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert sum(message in line for line in result.stderr.splitlines()) == 1


def test_a_hung_worker_costs_one_timeout_then_gets_no_query(weights_dir, tmp_path):
    """DESIGN: a hung worker costs at most one timeout. `a-hung` stops answering after one
    prediction but keeps its session, token and health probe (a deadlock, a stuck GPU)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    session = open_session(zenoh_config(listen=[endpoint], connect=[]))
    workers = WorkerPool(endpoint, weights_dir, tmp_path)
    client = None
    try:
        workers.start("g1", "a-hung", "--hang-after", "1")
        workers.start("g1", "b-good")
        client = ZenohEnsemble(session, FAST)
        for worker_id in ("a-hung", "b-good"):
            workers.wait_alive(client, "g1", worker_id)
        crop = partly_observed((40, 40))
        served = [client.predict(crop, members=(1,)).workers for _ in range(2)]
        assert served == [("a-hung",), ("b-good",)]  # least recently used: both in turn
        started = time.monotonic()
        assert client.predict(crop, members=(1,)).member_ids == ()  # a-hung: one timeout
        assert client.benched_workers()["g1"] == ("a-hung",)
        after = [client.predict(crop, members=(1,)).workers for _ in range(6)]
        elapsed = time.monotonic() - started
        assert after == [("b-good",)] * 6  # never asked again while it is stuck
        assert elapsed < 2 * FAST.predict_timeout_s, elapsed  # one timeout, not seven
        time.sleep(2 * FAST.health_probe_every_s)  # probes go out; it still reports busy
        assert client.predict(crop, members=(1,)).workers == ("b-good",)
        assert client.benched_workers()["g1"] == ("a-hung",)
        assert workers.processes["a-hung"].poll() is None
        assert "fault injection: hanging" in workers.log_of("a-hung")
    finally:
        if client is not None:
            client.close()
        workers.kill_all()
        session.close()


def test_sigterm_stops_a_worker_busy_on_a_prediction_without_waiting_for_it(weights_dir, tmp_path):
    """A worker stuck in a prediction (`--hang-after 0`) stops of SIGTERM within
    `predictor_drain_s` and a little: it leaves the prediction (its querier gets no reply)
    and skips the interpreter's teardown, so services.up's grace period never runs out."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    session = open_session(zenoh_config(listen=[endpoint], connect=[]))
    workers = WorkerPool(endpoint, weights_dir, tmp_path)
    try:
        process = workers.start("g", "busy", "--hang-after", "0")
        with ZenohEnsemble(session, FAST) as client:
            workers.wait_alive(client, "g", "busy")
        request = PredictRequest(1, partly_observed()).encode()
        pending = session.get(predict_key("g", "busy"), payload=request, timeout=30.0)
        until(lambda: "fault injection: hanging" in workers.log_of("busy"), "it to hang", 10)
        began = time.monotonic()
        process.send_signal(signal.SIGTERM)
        assert process.wait(STOP_DEADLINE_S) == 0
        stopped_s = time.monotonic() - began
        limit_s = DEFAULT_SERVICES.predictor_drain_s + STOP_SLACK_S
        assert stopped_s < limit_s <= DEFAULT_SERVICES.stop_grace_s, stopped_s
        assert [reply.ok for reply in pending if reply.ok is not None] == []
        log = workers.log_of("busy")
        assert "stopping without the prediction in progress" in log and "Traceback" not in log
    finally:
        workers.kill_all()
        session.close()


# ---------------------------------------------------------------------- in-process pieces


class ConstantPredictor(Predictor):
    """Every member predicts 0.25 everywhere."""

    def predict_members(self, observed, members):
        return np.full((len(members), *observed.shape), 0.25, dtype=np.float32)


@pytest.mark.parametrize("what", [*_malformed_payloads(), "no payload"])
def test_member_server_refuses_malformed_payloads(what):
    server = MemberServer(ConstantPredictor(), "g2", "w0")
    payload = None if what == "no payload" else _malformed_payloads()[what]
    reply = server.answer(payload)
    assert isinstance(reply, ErrorReply) and "\n" not in reply.message
    assert server.answered == 0


class SlowPredictor(ConstantPredictor):
    """`ConstantPredictor` that takes `delay_s` per prediction (the first `slow` ones)."""

    def __init__(self, delay_s: float, slow: int = 10**6) -> None:
        self.delay_s, self.slow, self.calls = delay_s, slow, 0

    def predict_members(self, observed, members):
        self.calls += 1
        if self.calls <= self.slow:
            time.sleep(self.delay_s)
        return super().predict_members(observed, members)


@contextlib.contextmanager
def serving(session, server: MemberServer):
    """`services.predictor.serve` of `server` on `session`, in a thread, until the block ends."""
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(session, server, stop), daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(STOP_DEADLINE_S)


def test_requests_that_waited_past_their_budget_are_dropped_not_computed(rogue_pair):
    planner, worker = rogue_pair
    predictor = SlowPredictor(delay_s=1.0)
    server = MemberServer(predictor, "g", "slow")
    with serving(worker, server):
        until(lambda: list(planner.liveliness().get(alive_predictor_key("g", "slow"))), "token")
        payloads = [
            PredictRequest(k, partly_observed((12, 10)), budget_s=0.5).encode() for k in (1, 2)
        ]
        pending = [planner.get(predict_key("g", "slow"), payload=p, timeout=5.0) for p in payloads]
        first, second = ([r for r in replies] for replies in pending)
    assert first[0].ok is not None  # computed
    dropped = decode_message(second[0].err.payload.to_bytes(), (ErrorReply,))
    assert dropped.message.startswith("dropped: waited")  # it waited ~1 s behind the first
    assert (predictor.calls, server.answered, server.dropped) == (1, 1, 1)


def test_a_benched_worker_is_back_after_its_bench_time_not_when_it_says_it_is_idle(rogue_pair):
    """Its health replies say idle once its slow prediction is done; it stays benched all
    the same until `bench_first_s` has passed, then a timely answer clears its record."""
    planner, worker = rogue_pair
    services = ServicesConfig(
        predict_timeout_s=0.5, liveliness_query_timeout_s=0.5, health_probe_every_s=0.1,
        bench_first_s=3.0, **UNCHECKED,
    )  # fmt: skip
    server = MemberServer(SlowPredictor(delay_s=1.0, slow=1), "g", "slow")
    with serving(worker, server), ZenohEnsemble(planner, services) as client:
        assert client.wait(timeout_s=5.0, members=("g",))
        crop = partly_observed((12, 10))
        benched_at = time.monotonic()
        assert client.predict(crop, members=(0,)).member_ids == ()  # 1 s > 0.5 s timeout
        assert client.benched_workers()["g"] == ("slow",)
        until(lambda: server.answered == 1, "the slow prediction to end", deadline_s=5.0)
        while time.monotonic() - benched_at < services.bench_first_s - 0.5:
            assert client.predict(crop, members=(0,)).member_ids == ()  # probes: "idle"
            assert client.benched_workers()["g"] == ("slow",)
            time.sleep(services.health_probe_every_s)
        until(lambda: client.benched_workers()["g"] == (), "the bench to end", deadline_s=5.0)
        assert client.predict(crop, members=(0,)).workers == ("slow",)
        assert ("g", "slow") not in client._standing  # a timely answer: a clean record


def test_health_says_how_long_the_current_prediction_runs():
    server = MemberServer(SlowPredictor(delay_s=0.6), "g3", "w0")
    assert server.health(queued=0) == HealthReply("g3", "w0", 0.0, 0, 0, 0)
    thread = threading.Thread(
        target=server.answer, args=(PredictRequest(1, partly_observed()).encode(),)
    )
    thread.start()
    time.sleep(0.3)
    busy = server.health(queued=2)
    thread.join()
    assert 0.2 < busy.busy_s < 0.6 and busy.queued == 2
    assert server.health(queued=0).answered == 1


def test_member_server_answers_a_request():
    server = MemberServer(ConstantPredictor(), "g2", "w0")
    reply = server.answer(PredictRequest(17, partly_observed((24, 30))).encode())
    assert isinstance(reply, PredictReply)
    assert (reply.request_id, reply.member, reply.worker_id) == (17, "g2", "w0")
    np.testing.assert_allclose(reply.probabilities(), 0.25, atol=1 / 510)
    assert server.answered == 1


def test_a_worker_answers_only_requests_for_the_predictor_it_serves():
    """A request names its predictor (absent: the default, lama): a worker serving another
    refuses it, so a planner never takes lama-v2's answer for lama's."""
    server = MemberServer(ConstantPredictor(), "g", "w0", serves="lama-v2")
    refused = server.answer(PredictRequest(1, partly_observed((12, 10))).encode())
    assert isinstance(refused, ErrorReply)
    assert refused.message == "this worker serves predictor lama-v2, not lama"
    taken = server.answer(
        PredictRequest(2, partly_observed((12, 10)), predictor="lama-v2").encode()
    )
    assert isinstance(taken, PredictReply) and server.answered == 1
    default = MemberServer(ConstantPredictor(), "g", "w1")  # serves lama
    answer = default.answer(
        PredictRequest(3, partly_observed((12, 10)), predictor="oracle").encode()
    )
    assert isinstance(answer, ErrorReply) and "not oracle" in answer.message


ROGUE_MODES = [
    "good", "garbage", "error", "wrong_request", "wrong_member", "wrong_shape", "wrong_worker",
]  # fmt: skip


@pytest.fixture
def rogue_pair():
    """A planner-side session and a second session where a hand-written 'worker' lives."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    planner = open_session(zenoh_config(listen=[endpoint], connect=[]))
    rogue = open_session(zenoh_config(connect=[endpoint]))
    yield planner, rogue
    rogue.close()
    planner.close()


def _rogue_reply(mode: str, request: PredictRequest) -> bytes:
    shape = (2, 2) if mode == "wrong_shape" else request.observed.shape
    request_id = request.request_id + (1 if mode == "wrong_request" else 0)
    member = "g1" if mode == "wrong_member" else "g"
    probabilities = np.full(shape, 0.5, dtype=np.float32)
    signed = "other" if mode == "wrong_worker" else "rogue"  # the id it answers under
    reply = PredictReply.from_probabilities(request_id, member, probabilities, signed, 1.0)
    return {"garbage": b"\x00garbage", "error": ErrorReply("busy").encode()}.get(
        mode, reply.encode()
    )


@contextlib.contextmanager
def rogue_worker(rogue, mode: str):
    """A hand-written live 'worker' of member g on session `rogue`, answering as `mode` says;
    a silent one never reads its queries (they wait unanswered until the client's timeout)."""
    key = predict_key("g", "rogue")

    def answer(query):
        request = PredictRequest.decode(query.payload.to_bytes())
        query.reply(key, _rogue_reply(mode, request))

    queryable = rogue.declare_queryable(key, None if mode == "silent" else answer)
    token = rogue.liveliness().declare_token(alive_predictor_key("g", "rogue"))
    try:
        yield
    finally:
        token.undeclare()
        queryable.undeclare()


@pytest.mark.parametrize("mode", [*ROGUE_MODES, "silent"])
def test_the_client_keeps_only_valid_replies(rogue_pair, mode):
    planner, rogue = rogue_pair
    services = ServicesConfig(
        predict_timeout_s=0.5, liveliness_query_timeout_s=0.5, **UNCHECKED
    )  # the rogue's "good" answer is 0.5 everywhere
    with rogue_worker(rogue, mode), ZenohEnsemble(planner, services) as client:
        assert client.wait(timeout_s=5.0, members=("g",))
        crop = partly_observed((12, 10))
        answers = client.predict(crop, members=(0, 1))  # g1 has no worker at all
        assert answers.member_ids == ((0,) if mode == "good" else ())
        if mode == "good":
            assert answers.workers == ("rogue",)
            unknown = crop == UNKNOWN
            np.testing.assert_allclose(answers.members[0][unknown], 0.5, atol=1 / 510)


@pytest.mark.parametrize("unrouted", [0, 1, 3, 4])
def test_a_query_left_unrouted_is_sent_again_up_to_the_retry_limit(rogue_pair, unrouted):
    planner, rogue = rogue_pair
    services = ServicesConfig(
        predict_timeout_s=2.0, liveliness_query_timeout_s=0.5, predict_retries=3,
        predict_retry_pause_s=0.01, **UNCHECKED,
    )  # fmt: skip
    session = UnroutedSession(planner, unrouted)
    with rogue_worker(rogue, "good"), ZenohEnsemble(session, services) as client:
        assert client.wait(timeout_s=5.0, members=("g",))
        answers = client.predict(partly_observed((12, 10)), members=(0,))
    answered = unrouted <= services.predict_retries
    assert answers.member_ids == ((0,) if answered else ())
    assert len(session.gets) == min(unrouted + 1, services.predict_retries + 1)
