"""services.health: the supervisor kills a worker stuck in a prediction, and restarts it.

A real predictor process (tiny random weights) with `--hang-after 0` is made to hang by one
query; the watch must find it busy past the limit, SIGKILL it, and the supervisor restart it.
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import torch
from service_processes import REPO_ROOT, free_loopback_port, until
from tiny_training import SMALL

from mapex.grid import FREE, UNKNOWN
from mapex.prediction.base import MEMBER_NAMES
from mapex.prediction.network import LamaGenerator
from mapex.prediction.weights import save_weights
from services.config import ServicesConfig
from services.ensemble_client import ZenohEnsemble
from services.health import PoolWatch
from services.keys import health_key
from services.messages import HealthReply
from services.pool import WorkerSpec
from services.supervisor import Supervisor
from services.zenoh_config import open_session, zenoh_config

WATCHED = ServicesConfig(
    predict_timeout_s=1.0,
    liveliness_query_timeout_s=0.5,
    health_check_every_s=0.3,
    health_probe_timeout_s=0.5,
    unresponsive_after_s=2.0,
    implausible_share=1.0,  # a random-weight network (services/ensemble_client.py)
    consensus_max_disagreement=1.0,
)
START_DEADLINE_S = 60.0


def test_a_worker_stuck_in_a_prediction_is_killed_and_restarted(tmp_path):
    torch.manual_seed(0)
    save_weights(tmp_path / "g2.pt", LamaGenerator(SMALL), {"member": MEMBER_NAMES[2]})
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    session = open_session(zenoh_config(listen=[endpoint], connect=[]))
    spec = WorkerSpec(
        "predictor-g2", "services.predictor",
        ("--member", "g2", "--worker-id", "stuck", "--weights-dir", str(tmp_path),
         "--hang-after", "0", "--connect", endpoint),
        restart=True, cwd=str(REPO_ROOT), member="g2", worker_id="stuck",
    )  # fmt: skip
    lines: list[str] = []
    lock = threading.Lock()

    def sink(line: str) -> None:
        with lock:
            lines.append(line)

    try:
        with (
            Supervisor(sink, services=WATCHED) as supervisor,
            ZenohEnsemble(session, WATCHED) as client,
        ):
            watch = PoolWatch(session, supervisor, [spec], WATCHED)
            supervisor.start(spec)
            first_pid = supervisor.process(spec.name).pid
            assert client.wait(START_DEADLINE_S, members=("g2",))

            def healthy_once_probed() -> bool:  # the watch must hear it before it hangs
                supervisor.poll()
                watch.check()
                return spec.name in watch._last_answer

            until(healthy_once_probed, "a first health answer", 10)
            observed = np.full((32, 32), UNKNOWN, dtype=np.uint8)
            observed[8:24, 8:24] = FREE
            assert client.predict(observed, members=(2,)).member_ids == ()  # it hangs

            def restarted() -> bool:
                supervisor.poll()
                watch.check()
                return supervisor.restarts.get(spec.name) == 1

            until(restarted, "the stuck worker to be killed and restarted", 30)
            assert supervisor.process(spec.name).pid != first_pid
            until(lambda: client.live_workers()["g2"] == ("stuck",), "the new worker", 60)
            until(healthy_once_probed, "the new worker's health answer", 10)
            assert client.benched_workers()["g2"] == ()  # a new incarnation starts unbenched
    finally:
        session.close()
    text = "\n".join(lines)
    assert "killing predictor-g2: unresponsive: busy on one prediction for" in text, text
    assert "predictor-g2 exited with -9 (SIGKILL); restarted (1/" in text, text


class StubSupervisor:
    """Every worker runs, as pid 1; kills are only noted."""

    def __init__(self) -> None:
        self.killed: list[str] = []

    def is_running(self, name: str) -> bool:
        return True

    def process(self, name: str) -> SimpleNamespace:
        return SimpleNamespace(pid=1)

    def kill(self, name: str, why: str) -> None:
        self.killed.append(name)


def test_a_health_reply_counts_only_if_it_names_the_worker_probed():
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    session = open_session(zenoh_config(listen=[endpoint], connect=[]))
    answering = open_session(zenoh_config(connect=[endpoint]))
    signer = {"worker_id": "impostor"}
    spec = WorkerSpec("predictor-g2", "services.predictor", member="g2", worker_id="w")

    def on_probe(query) -> None:
        query.reply(query.key_expr, HealthReply("g2", signer["worker_id"], 0, 0, 0, 0).encode())

    queryable = answering.declare_queryable(health_key("g2", "w"), on_probe)
    try:
        watch = PoolWatch(session, StubSupervisor(), [spec], WATCHED)
        for _ in range(3):
            watch.check()
            watch._next_check = 0.0
            threading.Event().wait(WATCHED.health_probe_timeout_s)
        assert spec.name not in watch._last_answer  # signed by another worker: ignored
        signer["worker_id"] = "w"

        def answered() -> bool:
            watch._next_check = 0.0
            watch.check()
            return spec.name in watch._last_answer

        until(answered, "the honest health reply", 5)
    finally:
        queryable.undeclare()
        answering.close()
        session.close()
