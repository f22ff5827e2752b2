"""services.planner: pieces that need no process, a planner refusing a world whose
sensor or motion differ from its own, and a planner whose world answers garbage or invalid
steps (a fake world: queryables of the test process) ending with one line, exit 1 (its
whole runs are tested in test_up.py)."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
from service_processes import ServiceProcesses

from mapex.config import WorldConfig
from mapex.worlds import load_world
from services.config import ServicesConfig
from services.keys import alive_world_key
from services.messages import STEP_REPLY_ARRAYS, PoseMessage, StepReply, StepRequest
from services.planner import prediction_size_warning
from services.world import WorldServer
from services.world_client import WorldUnavailableError, ZenohWorld
from services.zenoh_config import open_session, zenoh_config

RUN_DEADLINE_S = 120.0  # imports (torch) of a cold interpreter on a shared 2-core machine
RUN = "mismatch_test"


def test_maps_too_large_to_predict_in_time_are_flagged_with_the_limit():
    services = ServicesConfig(predict_max_cells=1000, predict_timeout_s=10.0)
    assert prediction_size_warning((25, 40), services) is None  # exactly at the limit
    warning = prediction_size_warning((30, 40), services)
    assert warning is not None and "\n" not in warning
    assert "1,200 cells, above the 1,000" in warning and "within 10 s" in warning
    assert "marked degraded from the start" in warning


def test_the_default_limit_leaves_every_world_the_size_limit_allows_unflagged():
    side = int(WorldConfig().max_cells ** 0.5)
    assert prediction_size_warning((side, side), ServicesConfig()) is None


@pytest.fixture(scope="module")
def world_process(hub, tmp_path_factory):
    """A world of the default settings serving RUN on the hub."""
    processes = ServiceProcesses(hub[1], tmp_path_factory.mktemp("logs"))
    try:
        processes.spawn("world", "services.world", "--run", RUN, "--world", "generated:0")

        def alive() -> bool:
            return bool(list(hub[0].liveliness().get(alive_world_key(RUN), timeout=1.0)))

        processes.wait_until_announced("world", alive, RUN_DEADLINE_S)
        yield processes
    finally:
        processes.kill_all()


@pytest.mark.parametrize(
    "settings, named",
    [
        (["sensor.n_rays=1000"], ["n_rays 2500 (here 1000)"]),
        (
            ["motion.cells_per_step=2", "sensor.range_cells=100", "services.step_retries=5"],
            ["range_cells 200 (here 100)", "cells_per_step 3 (here 2)"],
        ),
    ],
    ids=["sensor", "sensor-and-motion"],
)
def test_a_planner_with_other_settings_than_its_world_refuses_to_start(
    world_process, tmp_path, settings, named
):
    out = tmp_path / "runs" / "r0"
    name = f"planner-{len(settings)}"
    sets = [flag for item in settings for flag in ("--set", item)]
    process = world_process.spawn(
        name, "services.planner", "--run", RUN, "--method", "nearest", "--steps", "5",
        "--no-progress", "--out", str(out), *sets,
    )  # fmt: skip
    assert process.wait(RUN_DEADLINE_S) == 1, world_process.log_of(name)
    log = world_process.log_of(name)
    errors = [line for line in log.splitlines() if " ERROR " in line]
    assert len(errors) == 1 and "Traceback" not in log, log
    (error,) = errors
    assert f"the world of run {RUN} simulates " in error
    assert all(each in error for each in named), error
    assert "start the planner with the world's --set" in error
    assert not out.exists() and list(out.parent.iterdir()) == []  # nothing written
    assert world_process.processes["world"].poll() is None  # the world serves on
    (said,) = [line for line in log.splitlines() if " INFO settings: " in line]
    assert all(f" {item}" in said for item in ["steps=5", *settings]), said  # as it ran


# ------------------------------------------- a world that answers garbage or invalid steps

FAKE_WORLD = "generated:0"


def _reply_variants(server: WorldServer) -> dict[str, bytes]:
    """A valid step reply of seq 0 ("good") and invalid ones, by what is wrong."""
    good = server.answer_step(
        0, StepRequest(0, np.zeros((0, 2)), False, False, None, None, None).encode()
    )
    assert isinstance(good, StepReply)
    shape, rays = server.world.shape, good.n_cells.shape[1]
    wall = np.argwhere(server.world.occupancy)[0].astype(np.int32)

    def replaced(**fields) -> bytes:
        return dataclasses.replace(good, **fields).encode()

    def claimed(goal, score=1.0, visible_shape=shape) -> bytes:
        return replaced(
            claim_state=np.array([1], np.uint8),
            claim_goals=np.array([goal], np.int32),
            claim_scores=np.array([score]),
            claim_visible=np.zeros((1, *visible_shape), bool),
        )

    def twice(array: np.ndarray) -> np.ndarray:
        return np.concatenate([array, array])

    two = {name: twice(getattr(good, name)) for name, _, _ in STEP_REPLY_ARRAYS}
    two["claim_visible"] = good.claim_visible
    return {
        "good": good.encode(),
        "garbage": np.random.default_rng(5).bytes(300),
        "another type": PoseMessage(0, server.starts[0]).encode(),
        "another seq": replaced(seq=1),
        "two robots": StepReply(0, False, **two).encode(),
        "no scans": replaced(
            poses=np.zeros((0, 2), np.int32),
            n_cells=np.zeros((0, rays), np.uint16),
            hit=np.zeros((0, rays), bool),
        ),
        "other rays": replaced(n_cells=good.n_cells[:, :10].copy(), hit=good.hit[:, :10].copy()),
        "pose outside": replaced(poses=np.array([[shape[0] + 3, 0]], np.int32)),
        "negative pose": replaced(poses=np.array([[-1, 5]], np.int32)),
        "pose in a wall": replaced(poses=wall.reshape(1, 2)),
        "scan not the ground truth": replaced(n_cells=np.maximum(good.n_cells, 2) - 1),
        "claim outside": claimed((1, shape[1])),
        "claimed cells of another shape": claimed((1, 1), visible_shape=(4, 4)),
        "claim scored NaN": claimed((1, 1), math.nan),
    }


INVALID = {  # what the planner's one line says of each invalid reply
    "garbage": "msgpack",
    "another type": "expected a message of type step_reply, error, got 'pose'",
    "another seq": "step_reply of step 1, not of step 0",
    "two robots": "step_reply for 2 robots, the run has 1",
    "no scans": "step_reply with 0 scans, expected 1",
    "other rays": "step_reply scans of 10 rays, the sensor has 2500",
    "pose outside": "step_reply with a pose outside the (363, 537) map",
    "negative pose": "step_reply with a pose outside the (363, 537) map",
    "pose in a wall": "step_reply puts robot r0 in a wall at",
    "scan not the ground truth": "step_reply scan of robot r0 contradicts the ground truth",
    "claim outside": "step_reply with a claimed goal outside the (363, 537) map",
    "claimed cells of another shape": "claimed cells of another shape than the (363, 537) map",
    "claim scored NaN": "step_reply with a claim scored NaN or +inf",
}


def _run_of(case: str) -> str:
    """The run id of a case of `_reply_variants`."""
    return "fake-" + case.replace(" ", "-").lower()


@pytest.fixture(scope="module")
def fake_world(hub):
    """Queryables in the test process that serve a valid world_info and ground truth for
    the run of every case (`_run_of`) and answer its step queries with that case's reply."""
    server = WorldServer(load_world(FAKE_WORLD), [0])
    replies = {_run_of(case): reply for case, reply in _reply_variants(server).items()}
    info, truth = server.world_info().encode(), server.ground_truth().encode()

    def answer(payload_of):
        def reply(query) -> None:
            run = str(query.key_expr).split("/")[2]
            if run in replies:
                query.reply(query.key_expr, payload_of(run))

        return reply

    queryables = [
        hub[0].declare_queryable("mapex/@v1/*/world_info", answer(lambda _: info)),
        hub[0].declare_queryable("mapex/@v1/*/ground_truth", answer(lambda _: truth)),
        hub[0].declare_queryable("mapex/@v1/*/r0/step", answer(replies.__getitem__)),
    ]
    try:
        yield server
    finally:
        for queryable in queryables:
            queryable.undeclare()


def test_a_step_reply_that_fits_the_world_is_taken(hub, fake_world):
    session = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    try:
        source = ZenohWorld(session, _run_of("good"), 0)
        source.fetch(timeout_s=10.0)
        (scan,) = source.initial()
    finally:
        session.close()
    assert scan.pose == fake_world.starts[0]


@pytest.mark.parametrize("case", list(INVALID))
def test_an_invalid_step_reply_is_one_line_at_once(hub, fake_world, case):
    session = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    try:
        source = ZenohWorld(session, _run_of(case), 0)
        source.fetch(timeout_s=10.0)
        began = time.monotonic()
        with pytest.raises(WorldUnavailableError) as raised:
            source.initial()
        elapsed_s = time.monotonic() - began
    finally:
        session.close()
    message = str(raised.value)
    assert "\n" not in message and "the world's reply is invalid" in message
    assert INVALID[case] in message, message
    assert elapsed_s < ServicesConfig().step_timeout_s  # not asked again and again


@pytest.mark.parametrize("cases", [("garbage", "other rays", "pose outside")])
def test_a_planner_whose_world_answers_invalid_steps_exits_1_with_one_line(
    hub, fake_world, tmp_path, cases
):
    processes = ServiceProcesses(hub[1], tmp_path)
    try:
        for case in cases:
            processes.spawn(
                case, "services.planner", "--run", _run_of(case), "--method", "nearest",
                "--steps", "5", "--no-progress", "--out", str(tmp_path / "runs" / _run_of(case)),
                "--set", "services.workers_wait_s=0.5",
            )  # fmt: skip
        for case in cases:
            assert processes.processes[case].wait(RUN_DEADLINE_S) == 1, processes.log_of(case)
    finally:
        processes.kill_all()
    for case in cases:
        log = processes.log_of(case)
        errors = [line for line in log.splitlines() if " ERROR " in line]
        assert len(errors) == 1 and "Traceback" not in log, log
        assert "the world's reply is invalid" in errors[0] and INVALID[case] in errors[0], log
        assert not (tmp_path / "runs" / _run_of(case)).exists()


def test_a_step_query_that_times_out_is_asked_again_not_fatal(hub, fake_world):
    """Zenoh ends a query nobody answered in time with the error payload `Timeout`: the
    planner asks again (`step_retries` x `step_timeout_s`), it is not an invalid reply."""
    run, held = "fake-held-once", []
    good = _reply_variants(fake_world)["good"]
    info, truth = fake_world.world_info().encode(), fake_world.ground_truth().encode()

    def step(query) -> None:
        if not held:
            held.append(query)  # the first query: held past its timeout, never answered
        else:
            query.reply(query.key_expr, good)

    def serve(payload: bytes):
        return lambda query: query.reply(query.key_expr, payload)

    queryables = [
        hub[0].declare_queryable(f"mapex/@v1/{run}/world_info", serve(info)),
        hub[0].declare_queryable(f"mapex/@v1/{run}/ground_truth", serve(truth)),
        hub[0].declare_queryable(f"mapex/@v1/{run}/r0/step", step),
    ]
    session = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    services = ServicesConfig(step_timeout_s=0.5, team_step_wait_s=0.5)
    try:
        source = ZenohWorld(session, run, 0, services)
        source.fetch(timeout_s=10.0)
        (scan,) = source.initial()
    finally:
        session.close()
        for queryable in queryables:
            queryable.undeclare()
        held.clear()
    assert scan.pose == fake_world.starts[0]
