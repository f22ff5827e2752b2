"""The oracle worker (services/oracle_worker.py) and the planner's client under the oracle.

In-process pieces first (the refusals, the bounded cache of ground truths), then a worker
served in a thread of this process on one loopback session and a planner's `ZenohEnsemble`
on another: the answer is the truth and gives the in-process oracle's prediction, a wrong
one is refused and its worker benched, and an honest crop that the implausibility rules
would refuse (one value on every unknown cell) is taken. No torch anywhere.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import threading

import numpy as np
import pytest
from service_processes import REPO_ROOT, STOP_DEADLINE_S, free_loopback_port, until

from mapex.grid import FREE, OCCUPIED, UNKNOWN, quantise_probability
from mapex.prediction.oracle import OraclePrediction, OraclePredictor
from services.config import ServicesConfig
from services.ensemble_client import ZenohEnsemble, implausibility
from services.keys import alive_predictor_key, run_key
from services.messages import ErrorReply, GroundTruth, PredictReply, PredictRequest
from services.oracle_worker import (
    GroundTruths,
    OracleMember,
    RequestRefusedError,
    zenoh_truth_source,
)
from services.predictor import MemberServer, run_cli, serve
from services.zenoh_config import open_session, zenoh_config

QUICK = ServicesConfig(
    predict_timeout_s=3.0, liveliness_query_timeout_s=1.0, oracle_truth_wait_s=1.0
)
RUN = "oracle-run"


def building() -> tuple[np.ndarray, np.ndarray]:
    """(walls, observed): a hall with a pillar, its left part known."""
    walls = np.zeros((50, 80), dtype=bool)
    walls[[0, -1], :] = walls[:, [0, -1]] = True
    walls[20:30, 50:53] = True
    observed = np.full(walls.shape, UNKNOWN, dtype=np.uint8)
    observed[:, :30] = np.where(walls[:, :30], OCCUPIED, FREE)
    return walls, observed


def oracle_server(walls: np.ndarray, worker_id: str = "w-oracle") -> MemberServer:
    truths = GroundTruths(lambda run: walls if run == RUN else None, size=2)
    return MemberServer(OracleMember(truths), "g", worker_id, serves="oracle")


# ---------------------------------------------------------------------- in-process pieces


def test_the_oracle_answers_the_truth_of_the_crop_where_it_lies():
    walls, observed = building()
    reply = oracle_server(walls).answer(
        PredictRequest(1, observed[10:30, 40:70], 5.0, RUN, (10, 40), "oracle").encode()
    )
    assert isinstance(reply, PredictReply) and reply.member == "g"
    np.testing.assert_array_equal(reply.probabilities_u8, quantise_probability(walls[10:30, 40:70]))


@pytest.mark.parametrize(
    ("request_", "refusal"),
    [
        (PredictRequest(1, np.ones((4, 4), np.uint8)), "serves predictor oracle, not lama"),
        (PredictRequest(1, np.ones((4, 4), np.uint8), predictor="lama-v2"), "not lama-v2"),
        (
            PredictRequest(1, np.ones((4, 4), np.uint8), predictor="oracle"),
            "only a request naming its run and the crop's origin",
        ),
        (
            PredictRequest(1, np.ones((4, 4), np.uint8), None, RUN, (48, 10), "oracle"),
            "the 4x4 crop at (48, 10) falls outside the 50x80 map of run oracle-run",
        ),
        (
            PredictRequest(1, np.ones((4, 4), np.uint8), None, "another-run", (0, 0), "oracle"),
            "no ground truth for run another-run",
        ),
    ],
)
def test_the_oracle_refuses_what_it_cannot_answer_in_one_line(request_, refusal):
    server = oracle_server(building()[0])
    reply = server.answer(request_.encode())
    assert isinstance(reply, ErrorReply) and refusal in reply.message
    assert "\n" not in reply.message and server.answered == 0


def test_kept_walls_that_do_not_fit_are_fetched_again_and_a_crop_contradicting_them_refused():
    """A reused run id (a new world under an old `--run-prefix`): the kept walls contradict
    the crop's known cells, so they are fetched again; a crop that contradicts fresh walls
    too is refused."""
    walls, observed = building()
    worlds = [np.zeros_like(walls), walls]  # the run id's first world, then its current one
    fetched = []
    truths = GroundTruths(lambda run: fetched.append(run) or worlds[min(len(fetched), 2) - 1], 2)
    server = MemberServer(OracleMember(truths), "g", "w", serves="oracle")
    truths.walls(RUN)  # the first world's walls are kept
    request = PredictRequest(1, observed[:20, :30], None, RUN, (0, 0), "oracle")
    reply = server.answer(request.encode())
    assert isinstance(reply, PredictReply) and len(fetched) == 2
    np.testing.assert_array_equal(reply.probabilities_u8, quantise_probability(walls[:20, :30]))
    lying = observed[:20, :30].copy()
    lying[5, 5] = OCCUPIED  # a wall the truth does not have
    refused = server.answer(PredictRequest(2, lying, None, RUN, (0, 0), "oracle").encode())
    assert isinstance(refused, ErrorReply) and len(fetched) == 3
    assert "contradicts the ground truth of run oracle-run on 1 known cells" in refused.message


def test_a_few_runs_ground_truths_are_kept_and_a_missing_one_asked_again():
    fetched = []

    def fetch(run):
        fetched.append(run)
        return None if run == "none" else np.full((2, 2), run == "a")

    truths = GroundTruths(fetch, size=2)
    assert truths.walls("a").all() and not truths.walls("b").any()
    truths.walls("a")  # kept
    truths.walls("c")  # b, used least recently, goes
    assert truths.runs() == ("a", "c") and fetched == ["a", "b", "c"]
    for _ in range(2):
        with pytest.raises(RequestRefusedError, match="no ground truth for run none"):
            truths.walls("none")
    assert fetched == ["a", "b", "c", "none", "none"] and truths.runs() == ("a", "c")


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--member", "g1"], "served by member g only"),
        (["--member", "g", "--device", "cuda"], "no --weights-dir or --device"),
        (["--member", "g", "--precision", "bfloat16"], "only the 'lama' predictors"),
    ],
)
def test_bad_oracle_worker_flags_are_one_line_errors(flags, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run_cli(["--predictor", "oracle", *flags])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err.splitlines()[-1]


def test_classical_is_refused_by_a_worker_in_one_line(capsys):
    with pytest.raises(SystemExit) as exit_info:
        run_cli(["--member", "g", "--predictor", "classical"])
    assert exit_info.value.code == 2
    assert "runs in one process only" in capsys.readouterr().err.splitlines()[-1]


def test_the_oracle_worker_needs_no_torch():
    program = (
        "import sys, services.predictor as p, services.oracle_worker as o\n"
        "p.MemberServer(o.OracleMember(o.GroundTruths(lambda run: None, 1)), 'g', 'w')\n"
        "print('torch' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                          cwd=REPO_ROOT, timeout=120)  # fmt: skip
    assert done.returncode == 0 and done.stdout.strip() == "False", done.stderr


# ---------------------------------------------------------------------- over Zenoh


@pytest.fixture
def sessions():
    """A planner-side session that serves the hub, a worker's, and a world's."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    planner = open_session(zenoh_config(listen=[endpoint], connect=[]))
    worker = open_session(zenoh_config(connect=[endpoint]))
    world = open_session(zenoh_config(connect=[endpoint]))
    yield planner, worker, world
    for session in (world, worker, planner):
        session.close()


@contextlib.contextmanager
def serving(session, server: MemberServer):
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(session, server, stop, QUICK), daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(STOP_DEADLINE_S)


def test_the_distributed_oracle_reads_the_world_and_equals_the_in_process_one(sessions):
    planner, worker, world = sessions
    walls, observed = building()
    truth = GroundTruth(walls, ~walls).encode()
    served = world.declare_queryable(
        run_key(RUN, "ground_truth"), lambda q: q.reply(q.key_expr, truth)
    )
    truths = GroundTruths(zenoh_truth_source(worker, QUICK), QUICK.oracle_runs_kept)
    server = MemberServer(OracleMember(truths), "g", "w-oracle", serves="oracle")
    region = (5, 45, 10, 75)
    with serving(worker, server), ZenohEnsemble(planner, QUICK, "oracle", RUN, walls) as client:
        until(lambda: list(planner.liveliness().get(alive_predictor_key("g", "w-oracle"))), "token")
        assert client.wait(timeout_s=5.0) and client.served_members == ("g",)
        remote = client.predict(observed, region, (1, 2, 3))
    served.undeclare()
    local = OraclePredictor(walls).predict(observed, region, (1, 2, 3))
    assert isinstance(remote, OraclePrediction) and remote.answered == (1, 2, 3)
    np.testing.assert_array_equal(remote.members, local.members)
    np.testing.assert_array_equal(remote.variance, local.variance)
    assert remote.served_by() == {"g": "w-oracle"} and truths.runs() == (RUN,)


def test_a_wrong_oracle_answer_is_refused_but_an_honest_all_free_one_is_taken(sessions):
    planner, worker, _ = sessions
    walls, observed = building()
    liar = oracle_server(~walls, "w-liar")  # answers the walls inverted
    free_room = (5, 15, 35, 45)  # unknown cells there are all free: one value on all of them
    crop = observed[free_room[0] : free_room[1], free_room[2] : free_room[3]]
    honest_answer = quantise_probability(walls[5:15, 35:45])
    assert "one value" in implausibility(crop, honest_answer, QUICK)  # what it would say
    with ZenohEnsemble(planner, QUICK, "oracle", RUN, walls) as client:
        with serving(worker, liar):
            assert client.wait(timeout_s=10.0)
            refused = client.predict(observed, free_room, (1, 2, 3))
            assert refused.member_ids == () and client.benched_workers()["g"] == ("w-liar",)
        with serving(worker, oracle_server(walls, "w-honest")):
            until(lambda: "w-honest" in client.live_workers()["g"], "the honest worker")
            taken = client.predict(observed, free_room, (1, 2, 3))
    assert isinstance(taken, OraclePrediction) and taken.served_by() == {"g": "w-honest"}
    assert taken.variance[5:15, 35:45].all() and not taken.mean[5:15, 35:45].any()
