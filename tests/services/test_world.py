"""The world simulator as a real process on loopback, and its pure WorldServer.

The test process opens the hub session on a free loopback port and acts as the planner; world
processes are spawned with subprocess (never forked) against it and are all killed at teardown
whatever happens.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest
from service_processes import (
    REPO_ROOT,
    STOP_DEADLINE_S,
    ServiceProcesses,
    free_loopback_port,
    until,
)

from mapex.config import ExplorationConfig, SensorConfig
from mapex.simulator import Simulator
from mapex.worlds import load_world, start_poses
from services.codec import encode_array, pack_message
from services.config import ServicesConfig
from services.keys import alive_world_key, robot_id, robot_key, run_key
from services.messages import (
    ErrorReply,
    GroundTruth,
    Message,
    PoseMessage,
    ScanReply,
    StepRequest,
    WorldInfo,
    decode_message,
)
from services.world import StartError, WorldServer
from services.world_client import WorldUnavailableError, ZenohWorld
from services.zenoh_config import open_session, zenoh_config

WORLD_SPEC = "generated:3"
RUN = "world_test"
STARTS = (0, 2, 3)  # r0 drives and is compared, r1 retries, r2 takes the bad requests
QUERY_TIMEOUT_S = 5.0
START_DEADLINE_S = 60.0  # imports and numba cache loads on a shared 2-core machine
NEIGHBOURS = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc])


def random_walk(occupancy: np.ndarray, start, n_steps: int, cells_per_step: int, seed: int):
    """`n_steps` lists of up to `cells_per_step` 8-connected moves through free cells."""
    rng = np.random.default_rng(seed)
    pose, steps = np.array(start), []
    for _ in range(n_steps):
        cells = []
        for _ in range(rng.integers(1, cells_per_step + 1)):
            options = pose + NEIGHBOURS
            options = options[~occupancy[options[:, 0], options[:, 1]]]
            pose = options[rng.integers(len(options))]
            cells.append(pose)
        steps.append(np.array(cells, dtype=np.int32))
    return steps


class WorldProcesses(ServiceProcesses):
    """World processes spawned against one hub."""

    def start(self, run: str, starts: tuple[int, ...]):
        robots, start_list = str(len(starts)), [str(s) for s in starts]
        return self.spawn(
            run, "services.world", "--world", WORLD_SPEC, "--run", run,
            "--robots", robots, "--starts", *start_list,
        )  # fmt: skip

    def wait_alive(self, session, run: str) -> None:
        self.wait_until_announced(run, lambda: _token_alive(session, run), START_DEADLINE_S)


def _token_alive(session, run: str) -> bool:
    return bool(list(session.liveliness().get(alive_world_key(run), timeout=1.0)))


@pytest.fixture(scope="module")
def worlds(hub, tmp_path_factory):
    processes = WorldProcesses(hub[1], tmp_path_factory.mktemp("logs"))
    try:
        processes.start(RUN, STARTS)
        processes.start("sigint_test", (1,))
        for run in processes.processes:
            processes.wait_alive(hub[0], run)
        yield processes
    finally:
        processes.kill_all()


def _get(session, key: str, payload: bytes | None = None) -> Message:
    """The one reply to a query on `key`: its message, ok or error."""
    replies = list(session.get(key, payload=payload, timeout=QUERY_TIMEOUT_S))
    assert len(replies) == 1, key
    sample = replies[0].ok if replies[0].ok is not None else replies[0].err
    return decode_message(sample.payload.to_bytes())


def _step(session, robot: int, seq: int, cells) -> Message:
    return _get(session, robot_key(RUN, robot_id(robot), "step"), StepRequest(seq, cells).encode())


def _assert_same_scan(reply: Message, scan) -> None:
    assert isinstance(reply, ScanReply), reply
    assert reply.pose == tuple(int(v) for v in scan.pose)
    np.testing.assert_array_equal(reply.n_cells, scan.n_cells)
    np.testing.assert_array_equal(reply.hit, scan.hit)


# ---------------------------------------------------------------------- a real world process


def test_steps_give_the_scans_of_an_in_process_simulator(hub, worlds):
    session = hub[0]
    poses, scans = [], []
    pose_sub = session.declare_subscriber(
        robot_key(RUN, "r0", "pose"), lambda s: poses.append(s.payload.to_bytes())
    )
    scan_sub = session.declare_subscriber(
        robot_key(RUN, "r0", "scan"), lambda s: scans.append(s.payload.to_bytes())
    )
    info = _get(session, run_key(RUN, "world_info"))
    truth = _get(session, run_key(RUN, "ground_truth"))
    assert isinstance(info, WorldInfo) and isinstance(truth, GroundTruth)
    config = ExplorationConfig()
    world = truth.to_world(info.name, info.resolution_m)
    local = Simulator(world, [tuple(info.starts[0])], config.sensor, config.motion)
    walk = random_walk(truth.occupancy, info.starts[0], 6, config.motion.cells_per_step, seed=5)
    try:
        _assert_same_scan(_step(session, 0, 0, []), local.scan(0))
        for seq, cells in enumerate(walk, start=1):
            _assert_same_scan(_step(session, 0, seq, cells), local.step(0, cells))
        until(lambda: len(poses) == len(scans) == len(walk) + 1, "the published steps")
    finally:
        pose_sub.undeclare()
        scan_sub.undeclare()
    published = [PoseMessage.decode(p) for p in poses]
    assert [(m.t, m.pose) for m in published[-2:]] == [
        (len(walk) - 1, tuple(map(int, walk[-2][-1]))),
        (len(walk), tuple(map(int, walk[-1][-1]))),
    ]
    assert ScanReply.decode(scans[-1]).pose == published[-1].pose


def test_a_repeated_seq_returns_the_same_scan_without_moving(hub, worlds):
    session = hub[0]
    truth = _get(session, run_key(RUN, "ground_truth"))
    start = _get(session, run_key(RUN, "world_info")).starts[1]
    first, second = random_walk(truth.occupancy, start, 2, 3, seed=11)
    assert isinstance(_step(session, 1, 0, []), ScanReply)
    moved = _step(session, 1, 1, first)
    again = _step(session, 1, 1, first)
    also = _step(session, 1, 1, [])  # the cells of a retry do not matter: nothing moves
    for reply in (again, also):
        assert reply.pose == moved.pose == tuple(map(int, first[-1]))
        np.testing.assert_array_equal(reply.n_cells, moved.n_cells)
    assert _step(session, 1, 2, second).pose == tuple(map(int, second[-1]))


def _bad_payloads(pose) -> dict[str, bytes]:
    row, col = pose
    far_jump = StepRequest(1, [[row, col + 2]])
    float_cells = {"seq": 1, "cells": encode_array(np.zeros((1, 2), np.float32))}
    return {
        "bad move": far_jump.encode(),
        "skipped seq": StepRequest(5, []).encode(),
        "random bytes": np.random.default_rng(3).bytes(200),
        "wrong schema": msgpack.packb({"schema": 99, "type": "step_request", "seq": 1}),
        "wrong type": ErrorReply("not a step").encode(),
        "wrong dtype": pack_message("step_request", float_cells),
    }


def test_bad_requests_get_an_error_reply_and_the_world_answers_on(hub, worlds):
    session, key = hub[0], robot_key(RUN, "r2", "step")
    start = _get(session, run_key(RUN, "world_info")).starts[2]
    initial = _step(session, 2, 0, [])
    assert isinstance(initial, ScanReply)
    for what, payload in _bad_payloads(start).items():
        reply = _get(session, key, payload)
        assert isinstance(reply, ErrorReply), what
        expected = {"bad move": "not one move", "skipped seq": "out of order"}
        assert expected.get(what, "malformed step request") in reply.message, what
    assert isinstance(_get(session, key), ErrorReply)  # no payload at all
    assert worlds.processes[RUN].poll() is None
    assert _step(session, 2, 0, []).pose == initial.pose  # never moved
    truth = _get(session, run_key(RUN, "ground_truth"))
    (cells,) = random_walk(truth.occupancy, start, 1, 3, seed=2)
    assert _step(session, 2, 1, cells).pose == tuple(map(int, cells[-1]))
    assert "refused a malformed step request" in worlds.log_of(RUN)


def test_a_late_joiner_gets_world_info_and_ground_truth(hub, worlds):
    late = open_session(zenoh_config(connect=[hub[1]]))
    try:
        info = until(lambda: _try_get(late, run_key(RUN, "world_info")), "world_info")
        truth = until(lambda: _try_get(late, run_key(RUN, "ground_truth")), "ground_truth")
    finally:
        late.close()
    world = load_world(WORLD_SPEC)
    expected_starts = [
        start_poses(world, ExplorationConfig().world.start_clearance_cells)[i] for i in STARTS
    ]
    assert (info.name, info.shape, info.resolution_m) == (
        world.name,
        world.shape,
        world.resolution_m,
    )
    np.testing.assert_array_equal(info.starts, expected_starts)
    np.testing.assert_array_equal(truth.occupancy, world.occupancy)
    np.testing.assert_array_equal(truth.valid_space, world.valid_space)


def _try_get(session, key: str) -> Message | None:
    replies = list(session.get(key, timeout=1.0))
    return decode_message(replies[0].ok.payload.to_bytes()) if replies else None


def test_sigint_stops_the_world_cleanly(hub, worlds):
    process = worlds.processes["sigint_test"]
    process.send_signal(signal.SIGINT)
    assert process.wait(STOP_DEADLINE_S) == 0
    assert not _token_alive(hub[0], "sigint_test")
    log = worlds.log_of("sigint_test")
    assert "stopped after serving 0 steps" in log and "Traceback" not in log


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--world", "generated:x"], "bad generated seed 'x'"),
        (["--world", "{missing}"], "no such map directory"),
        (["--starts", "7"], "corners are 0-3"),
        (["--starts", "0,1"], "start cell (0, 1) is on a wall"),
        (["--robots", "2", "--starts", "0"], "names 1 starts for 2 robots"),
        (["--run", "predict"], "--run 'predict' must match"),
    ],
)
def test_bad_world_starts_and_flags_are_one_line_errors(flags, message, tmp_path):
    flags = [f.format(missing=tmp_path / "none") for f in flags]
    if "--run" not in flags:
        flags += ["--run", "bad_flags"]
    result = subprocess.run(
        [sys.executable, "-m", "services.world", *flags, "--connect", "tcp/127.0.0.1:1"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert sum(message in line for line in result.stderr.splitlines()) == 1


# ---------------------------------------------------------------------- the pure WorldServer


SMALL = ExplorationConfig(sensor=SensorConfig(n_rays=90, range_cells=40))


@pytest.fixture(scope="module")
def world():
    return load_world(WORLD_SPEC)


def test_world_server_serves_fresh_steps_once_and_caches_retries(world):
    heard = []
    server = WorldServer(world, [0], SMALL, on_step=lambda *event: heard.append(event))
    start = server.starts[0]
    (cells,) = random_walk(world.occupancy, start, 1, 3, seed=1)
    first = server.answer_step(0, StepRequest(0, []).encode())
    assert first.pose == start
    assert server.answer_step(0, StepRequest(0, cells).encode()) is first  # a retry: cached
    moved = server.answer_step(0, StepRequest(1, cells).encode())
    assert moved.pose == tuple(map(int, cells[-1]))
    assert [(robot, seq) for robot, seq, _ in heard] == [(0, 0), (0, 1)]
    assert heard[-1][2] is moved and server.served == 2


@pytest.mark.parametrize(
    "robot, payload, match",
    [
        (0, StepRequest(1, []).encode(), "seq 1 is out of order, expected 0"),
        (0, None, "carries no payload"),
        (0, b"\x93garbage", "malformed step request"),
        (1, StepRequest(0, []).encode(), "robot 1 is not one of 0-0"),
        (-1, StepRequest(0, []).encode(), "robot -1 is not one of"),
        (0, StepRequest(0, [[0, 0]]).encode(), "refused motion"),
    ],
)
def test_world_server_refuses_bad_requests_without_raising(world, robot, payload, match):
    server = WorldServer(world, [0], SMALL)
    reply = server.answer_step(robot, payload)
    assert isinstance(reply, ErrorReply) and match in reply.message
    assert "\n" not in reply.message and server.served == 0
    assert tuple(server.simulator.poses[0]) == server.starts[0]


@pytest.mark.parametrize("token", [None, "", "wrong", "s3cret-but-longer"])
def test_a_world_with_a_run_token_refuses_steps_without_it(world, token):
    server = WorldServer(world, [0], SMALL, run_token="s3cret")
    reply = server.answer_step(0, StepRequest(0, [], token).encode())
    assert isinstance(reply, ErrorReply) and "without this run's token" in reply.message
    assert server.served == 0 and server._last_seq == [None]  # nothing moved, seq untouched
    assert isinstance(server.answer_step(0, StepRequest(0, [], "s3cret").encode()), ScanReply)


def test_world_server_knows_its_robots_starts_and_world(world):
    server = WorldServer(world, [3, 1], SMALL)
    corners = start_poses(world, SMALL.world.start_clearance_cells)
    assert server.starts == [corners[3], corners[1]] and server.n_robots == 2
    np.testing.assert_array_equal(server.world_info().starts, [corners[3], corners[1]])
    np.testing.assert_array_equal(server.ground_truth().occupancy, world.occupancy)


@pytest.mark.parametrize(
    "starts, match",
    [
        ([4], "start 4 is not a corner 0-3"),
        ([(0, 0)], r"start cell \(0, 0\) is on a wall"),
        ([], "one robot"),
    ],
)
def test_world_server_refuses_bad_starts(world, starts, match):
    with pytest.raises(StartError, match=match):
        WorldServer(world, starts, SMALL)


def test_a_gone_world_is_asked_again_with_back_off_for_the_whole_wait():
    """A step query nobody serves returns at once: the planner keeps asking, with growing
    pauses, until step_retries x step_timeout_s has passed, and says so honestly."""
    services = ServicesConfig(step_timeout_s=0.5, step_retries=2, step_retry_pause_s=(0.05, 0.2))
    session = open_session(zenoh_config("peer", [], [f"tcp/127.0.0.1:{free_loopback_port()}"]))
    try:
        began = time.monotonic()
        with pytest.raises(WorldUnavailableError) as info:
            ZenohWorld(session, "nobody", services).scan(0)
        elapsed_s = time.monotonic() - began
    finally:
        session.close()
    found = re.search(r"did not answer step 0 in ([\d.]+) s \((\d+) queries\)", str(info.value))
    assert found is not None, str(info.value)
    assert 0.8 <= float(found.group(1)) <= elapsed_s + 0.05 <= 5.0
    assert int(found.group(2)) >= 4  # asked again and again, not three times in a few ms
