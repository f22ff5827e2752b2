"""The world simulator as a real process on loopback, and its pure lockstep WorldServer.

The test process opens the hub session on a free loopback port and acts as the planners;
world processes are spawned with subprocess (never forked) against it and are all killed at
teardown whatever happens. A world answers the step of seq s once every robot of its team
has asked for it (or `services.team_step_wait_s` has passed), so a test that drives a team
sends every robot's request from a thread of its own, as the robots' planners do.
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
from commands_at_once import run_python_m
from service_processes import (
    REPO_ROOT,
    STOP_DEADLINE_S,
    ServiceProcesses,
    free_loopback_port,
    until,
)

from mapex.config import ExplorationConfig, MotionConfig, SensorConfig
from mapex.methods.claims import Claim
from mapex.simulator import Simulator
from mapex.team.starts import team_start_cells
from mapex.team.team import Decision
from mapex.worlds import load_world, start_poses
from services.codec import encode_array, pack_message
from services.config import ServicesConfig
from services.keys import alive_planner_key, alive_world_key, robot_id, robot_key, run_key
from services.messages import (
    ErrorReply,
    GroundTruth,
    Message,
    PoseMessage,
    ScanReply,
    StepReply,
    StepRequest,
    WorldInfo,
    decode_message,
    step_key,
)
from services.serving import RUN_TOKEN_ENV
from services.world import StartError, WorldServer, serve
from services.world_client import WorldUnavailableError, ZenohWorld
from services.zenoh_config import open_session, zenoh_config

WORLD_SPEC = "generated:3"
QUERY_TIMEOUT_S = 5.0  # well below the default team_step_wait_s: a test never waits on it
START_DEADLINE_S = 60.0  # imports and numba cache loads on a shared 2-core machine
NEIGHBOURS = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc])
DEFAULTS = ExplorationConfig()

# the world processes: run -> (starts, --set items); each test drives a world of its own
DRIVE, RETRY, BAD, SET, SIGINT = "drive_test", "retry_test", "bad_test", "set_test", "sigint_test"
SNIFFED = "sniffed_test"  # a team world with a run token, whose step queries are read
SNIFFED_TOKEN = "the-victim-s-run-token-7d1e0c"
FORGED, FORGED_PLAIN = "forged_test", "forged_plain_test"  # rogues answer their step queries
FORGED_TOKEN = "the-forged-run-s-token-51aa3f"
SET_ITEMS = ("motion.cells_per_step=2", "sensor.n_rays=360", "services.team_step_wait_s=0.5")
WORLDS = {
    DRIVE: ((0, 2), ()),  # a team of two, both driven in lockstep and compared
    RETRY: ((2,), ()),
    BAD: ((3,), ()),
    SET: ((1, 3), SET_ITEMS),  # only r0 drives: r1 is waited for 0.5 s, then stands still
    SIGINT: ((1,), ()),
    SNIFFED: ((0, 2), ()),
    FORGED: ((0,), ()),
    FORGED_PLAIN: ((0,), ()),
}
TOKENS = {
    SNIFFED: SNIFFED_TOKEN,
    FORGED: FORGED_TOKEN,
}  # MAPEX_RUN_TOKEN of the world processes that have one


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


def unsigned_request(seq: int, cells=(), done=False, claim=None) -> StepRequest:
    """A step request through `cells`; `claim` (goal, score, claimed cells) a new claim."""
    goal, score, visible = claim if claim is not None else (None, None, None)
    cells = np.asarray(cells, dtype=np.int32).reshape(-1, 2)
    return StepRequest(seq, cells, done, claim is not None, goal, score, visible)


def step_request(
    seq: int, cells=(), done=False, claim=None, token: str | None = None, run="", robot=0
) -> bytes:
    """`unsigned_request` encoded; with `token`, signed as robot `robot` of `run`."""
    request = unsigned_request(seq, cells, done, claim)
    if token is not None:
        request = request.signed(step_key(token, run), run, robot)
    return request.encode()


class WorldProcesses(ServiceProcesses):
    """World processes spawned against one hub."""

    def start(
        self,
        run: str,
        starts: tuple[int, ...],
        settings: tuple[str, ...] = (),
        token: str | None = None,
    ):
        """`services.world` serving `run`; with `token` as its MAPEX_RUN_TOKEN, as services.up
        starts it."""
        sets = [flag for item in settings for flag in ("--set", item)]
        command = [
            sys.executable, "-m", "services.world", "--world", WORLD_SPEC, "--run", run,
            "--robots", str(len(starts)), "--starts", *map(str, starts), *sets,
            "--connect", self.hub_endpoint,
        ]  # fmt: skip
        env = {k: v for k, v in os.environ.items() if k != RUN_TOKEN_ENV}
        if token is not None:
            env[RUN_TOKEN_ENV] = token
        with open(self.log_path(run), "wb") as log:
            process = subprocess.Popen(command, cwd=REPO_ROOT, stdout=log, stderr=log, env=env)
        self.processes[run] = process
        return process

    def wait_alive(self, session, run: str) -> None:
        self.wait_until_announced(run, lambda: _token_alive(session, run), START_DEADLINE_S)


def _token_alive(session, run: str) -> bool:
    return bool(list(session.liveliness().get(alive_world_key(run), timeout=1.0)))


@pytest.fixture(scope="module")
def worlds(hub, tmp_path_factory):
    processes = WorldProcesses(hub[1], tmp_path_factory.mktemp("logs"))
    try:
        for run, (starts, settings) in WORLDS.items():
            processes.start(run, starts, settings, TOKENS.get(run))
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


def _step(session, run: str, robot: int, seq: int, cells=()) -> Message:
    return _get(session, robot_key(run, robot_id(robot), "step"), step_request(seq, cells))


def _step_together(session, run: str, seq: int, cells: list) -> list[Message]:
    """Every robot's step `seq` (robot i through cells[i]), each asked from its own thread."""
    replies: dict[int, Message] = {}

    def ask(robot: int) -> None:
        replies[robot] = _step(session, run, robot, seq, cells[robot])

    threads = [threading.Thread(target=ask, args=(robot,)) for robot in range(len(cells))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(QUERY_TIMEOUT_S + 5)
    return [replies[robot] for robot in range(len(cells))]


def _assert_same_scans(reply: Message, scans: list) -> None:
    assert isinstance(reply, StepReply), reply
    assert len(reply.poses) == len(scans)
    for robot, scan in enumerate(scans):
        assert tuple(reply.poses[robot]) == tuple(int(v) for v in scan.pose), robot
        np.testing.assert_array_equal(reply.n_cells[robot], scan.n_cells)
        np.testing.assert_array_equal(reply.hit[robot], scan.hit)


def _assert_same_scan(scan, expected) -> None:
    assert tuple(int(v) for v in scan.pose) == tuple(int(v) for v in expected.pose)
    np.testing.assert_array_equal(scan.n_cells, expected.n_cells)
    np.testing.assert_array_equal(scan.hit, expected.hit)


def _fetch(session, run: str) -> tuple[WorldInfo, GroundTruth]:
    info, truth = (
        _get(session, run_key(run, "world_info")),
        _get(session, run_key(run, "ground_truth")),
    )
    assert isinstance(info, WorldInfo) and isinstance(truth, GroundTruth)
    return info, truth


# ---------------------------------------------------------------------- a real world process


def test_a_team_s_steps_give_the_scans_of_an_in_process_simulator(hub, worlds):
    session = hub[0]
    info, truth = _fetch(session, DRIVE)
    published: dict[tuple[int, str], list[bytes]] = {}
    subscribers = [
        session.declare_subscriber(
            robot_key(DRIVE, robot_id(robot), topic),
            lambda s, k=(robot, topic): published.setdefault(k, []).append(s.payload.to_bytes()),
        )
        for robot in (0, 1)
        for topic in ("pose", "scan")
    ]
    world = truth.to_world(info.name, info.resolution_m)
    starts = [tuple(map(int, start)) for start in info.starts]
    local = Simulator(world, starts, DEFAULTS.sensor, DEFAULTS.motion)
    walks = [
        random_walk(truth.occupancy, start, 6, 3, seed=5 + k) for k, start in enumerate(starts)
    ]
    try:
        first = _step_together(session, DRIVE, 0, [[], []])
        for reply in first:  # every robot gets the one reply: every robot's scan
            _assert_same_scans(reply, [local.scan(0), local.scan(1)])
        for seq in range(1, 7):
            cells = [walks[0][seq - 1], walks[1][seq - 1]]
            replies = _step_together(session, DRIVE, seq, cells)
            expected = [local.step(robot, cells[robot]) for robot in (0, 1)]
            for reply in replies:
                _assert_same_scans(reply, expected)
                assert reply.seq == seq and not reply.finished
                assert not reply.stood_still.any() and not reply.lost.any()
                assert not reply.claim_state.any()  # nobody claimed
        until(
            lambda: all(
                len(published.get((r, t), ())) == 7 for r in (0, 1) for t in ("pose", "scan")
            ),
            "the published steps",
        )
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
    for robot in (0, 1):
        poses = [PoseMessage.decode(p) for p in published[robot, "pose"]]
        assert [m.t for m in poses] == list(range(7))  # t = seq: the initial scan is t = 0
        assert poses[-1].pose == tuple(map(int, walks[robot][-1][-1]))
        assert ScanReply.decode(published[robot, "scan"][-1]).pose == poses[-1].pose


def test_a_repeated_seq_returns_the_same_step_without_moving(hub, worlds):
    session = hub[0]
    info, truth = _fetch(session, RETRY)
    first, second = random_walk(truth.occupancy, info.starts[0], 2, 3, seed=11)
    assert isinstance(_step(session, RETRY, 0, 0), StepReply)
    moved = _step(session, RETRY, 0, 1, first)
    again = _step(session, RETRY, 0, 1, first)
    also = _step(session, RETRY, 0, 1)  # the cells of a retry do not matter: nothing moves
    for reply in (moved, again, also):
        assert isinstance(reply, StepReply) and reply.seq == 1
        assert tuple(reply.poses[0]) == tuple(map(int, first[-1]))
        np.testing.assert_array_equal(reply.n_cells, moved.n_cells)
    assert tuple(_step(session, RETRY, 0, 2, second).poses[0]) == tuple(map(int, second[-1]))
    assert tuple(_step(session, RETRY, 0, 1, first).poses[0]) == tuple(map(int, first[-1]))


def _bad_payloads() -> dict[str, bytes]:
    float_cells = {"seq": 1, "cells": encode_array(np.zeros((1, 2), np.float32))}
    request = msgpack.unpackb(step_request(1))
    old = {k: request[k] for k in ("schema", "type", "seq", "cells")}
    return {
        "skipped seq": step_request(5),
        "random bytes": np.random.default_rng(3).bytes(200),
        "wrong schema": msgpack.packb({"schema": 99, "type": "step_request", "seq": 1}),
        "wrong type": ErrorReply("not a step").encode(),
        "wrong dtype": pack_message("step_request", float_cells),
        "single-robot request of before": msgpack.packb(old),
        "team request of before": msgpack.packb({**request, "type": "team_step_request"}),
    }


def test_bad_requests_get_an_error_reply_and_the_world_answers_on(hub, worlds):
    session, key = hub[0], robot_key(BAD, "r0", "step")
    info, truth = _fetch(session, BAD)
    start = tuple(map(int, info.starts[0]))
    initial = _step(session, BAD, 0, 0)
    assert isinstance(initial, StepReply)
    visible = np.zeros(info.shape, dtype=bool)
    misfits = {  # well-formed requests whose claim does not fit this world
        "claimed cells of another shape": step_request(1, claim=((5, 5), 1.0, visible[:9, :7])),
        "claim goal below the map": step_request(1, claim=((info.shape[0], 5), 1.0, visible)),
        "claim goal right of the map": step_request(1, claim=((5, 10**6), 1.0, visible)),
    }
    expected = {
        "skipped seq": "out of order",
        "no payload": "carries no payload",
        "claimed cells of another shape": f"claim_visible has shape (9, 7), the map {info.shape}",
        "claim goal below the map": f"lies outside the {info.shape} map",
        "claim goal right of the map": f"lies outside the {info.shape} map",
    }
    for what, payload in [*_bad_payloads().items(), *misfits.items(), ("no payload", None)]:
        reply = _get(session, key, payload)
        assert isinstance(reply, ErrorReply), what
        assert expected.get(what, "malformed step request") in reply.message, what
    assert worlds.processes[BAD].poll() is None
    again = _step(session, BAD, 0, 0)  # the initial step, as cached
    assert again.seq == 0 and tuple(again.poses[0]) == start  # never moved
    far_jump = _step(session, BAD, 0, 1, [[start[0], start[1] + 2]])  # a refused motion:
    assert isinstance(far_jump, StepReply) and tuple(far_jump.poses[0]) == start  # stood
    (cells,) = random_walk(truth.occupancy, start, 1, 3, seed=2)
    assert tuple(_step(session, BAD, 0, 2, cells).poses[0]) == tuple(map(int, cells[-1]))
    log = worlds.log_of(BAD)
    assert "refused a malformed step request" in log
    assert "robot r0: refused motion of step 1" in log and "Traceback" not in log
    assert "claim_visible has shape (9, 7)" in log


def test_a_world_started_with_set_simulates_and_waits_as_set(hub, worlds):
    """`--set` reaches the world: its sensor and motion (said in world_info, applied to
    every step) and its services section (how long a step waits for a late robot)."""
    session = hub[0]
    info, truth = _fetch(session, SET)
    assert info.settings() == {"n_rays": 360, "range_cells": 200, "cells_per_step": 2}
    world = truth.to_world(info.name, info.resolution_m)
    starts = [tuple(map(int, start)) for start in info.starts]
    local = Simulator(world, starts, SensorConfig(n_rays=360), MotionConfig(cells_per_step=2))
    walk = random_walk(truth.occupancy, starts[0], 3, 1, seed=7)
    two, three = np.concatenate(walk[:2]), np.concatenate(walk)  # 2 and 3 cells in one step
    timed = []
    for seq, cells in enumerate([[], three, two]):
        began = time.monotonic()
        reply = _step(session, SET, 0, seq, cells)  # r1 never asks
        timed.append(time.monotonic() - began)
        assert isinstance(reply, StepReply) and list(reply.stood_still) == [False, True]
        if seq == 1:  # 3 cells where 2 are allowed: refused, r0 stands still
            expected = [local.scan(0), local.scan(1)]
        else:
            expected = [local.scan(0) if seq == 0 else local.step(0, cells), local.scan(1)]
        _assert_same_scans(reply, expected)
        assert reply.n_cells.shape == (2, 360)
    assert all(0.4 <= wait_s < QUERY_TIMEOUT_S for wait_s in timed), timed  # not 10 s
    log = worlds.log_of(SET)
    assert all(item in log for item in SET_ITEMS), log  # the world's settings line
    assert "refused motion of step 1" in log
    assert "no request from r1 in time: standing still" in log


def test_a_late_joiner_gets_world_info_and_ground_truth(hub, worlds):
    late = open_session(zenoh_config(connect=[hub[1]]))
    try:
        info = until(lambda: _try_get(late, run_key(DRIVE, "world_info")), "world_info")
        truth = until(lambda: _try_get(late, run_key(DRIVE, "ground_truth")), "ground_truth")
    finally:
        late.close()
    world = load_world(WORLD_SPEC)
    corners = start_poses(world, DEFAULTS.world.start_clearance_cells)
    assert (info.name, info.shape, info.resolution_m) == (
        world.name,
        world.shape,
        world.resolution_m,
    )
    np.testing.assert_array_equal(info.starts, [corners[i] for i in WORLDS[DRIVE][0]])
    assert info.settings() == {
        "n_rays": DEFAULTS.sensor.n_rays,
        "range_cells": DEFAULTS.sensor.range_cells,
        "cells_per_step": DEFAULTS.motion.cells_per_step,
    }
    np.testing.assert_array_equal(truth.occupancy, world.occupancy)
    np.testing.assert_array_equal(truth.valid_space, world.valid_space)


def _try_get(session, key: str) -> Message | None:
    replies = list(session.get(key, timeout=1.0))
    return decode_message(replies[0].ok.payload.to_bytes()) if replies else None


def _team_step(sources: list[ZenohWorld], seq: int, walks: list) -> list:
    """Every robot's step `seq` through its ZenohWorld (robot k along walks[k]), each from
    a thread of its own as the planners do; the WorldSteps."""
    steps: dict[int, object] = {}

    def step(robot: int) -> None:
        if seq == 0:
            steps[robot] = sources[robot].initial()
        else:
            decision = Decision(robot, walks[robot][seq - 1])
            steps[robot] = sources[robot].step(seq - 1, [decision])

    threads = [threading.Thread(target=step, args=(k,)) for k in range(len(sources))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(QUERY_TIMEOUT_S + 5)
    return [steps[k] for k in range(len(sources))]


def test_a_sniffer_of_step_queries_can_neither_read_the_token_nor_step_a_robot(hub, worlds):
    """A client of a plain hub that reads every step query of a run with a token (as the
    `runner` role may under the ACL router) finds no token in them, and nothing it builds
    from them moves a robot: the victims' run goes on as if it had not been there."""
    session = hub[0]
    info, truth = _fetch(session, SNIFFED)
    starts = [tuple(map(int, start)) for start in info.starts]
    walks = [
        random_walk(truth.occupancy, start, 6, 3, seed=20 + k) for k, start in enumerate(starts)
    ]
    sources = [ZenohWorld(session, SNIFFED, k, run_token=SNIFFED_TOKEN) for k in (0, 1)]
    for source in sources:
        source.fetch(timeout_s=10.0)
    sniffer = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    captured: list[tuple[str, bytes]] = []

    def sniff(query) -> None:  # reads the query and answers nothing
        payload = b"" if query.payload is None else query.payload.to_bytes()
        captured.append((str(query.key_expr), payload))

    queryable = sniffer.declare_queryable(f"mapex/@v1/{SNIFFED}/*/step", sniff)
    try:
        time.sleep(0.5)  # the sniffer's queryable is known to the hub
        victims = [_team_step(sources, seq, walks) for seq in range(4)]
        heard = list(captured)
        # (a) the token is not in what travels, nor the key made from it
        key = step_key(SNIFFED_TOKEN, SNIFFED)
        assert len(heard) >= 8, heard  # two robots, four steps
        for _, payload in heard:
            assert SNIFFED_TOKEN.encode() not in payload and key not in payload
            assert key.hex().encode() not in payload
            assert StepRequest.decode(payload).mac is not None
        # (b) what the sniffer builds from them is refused
        by_robot_seq = {
            (str(k).rsplit("/", 2)[1], StepRequest.decode(p).seq): StepRequest.decode(p)
            for k, p in heard
        }
        last = by_robot_seq["r0", 3]  # robot 0's request of step 3; the world is at step 4
        (toward,) = random_walk(truth.occupancy, victims[3][0].scans[0].pose, 1, 1, seed=9)
        attacks = {
            "r0": {
                "its mac on the next seq": dataclasses.replace(last, seq=4),
                "its mac on the next seq, moving": dataclasses.replace(last, seq=4, cells=toward),
                "its mac on other cells": dataclasses.replace(last, cells=toward),
                "its mac on a claim": dataclasses.replace(
                    last,
                    seq=4,
                    claimed=True,
                    claim_goal=(5, 5),
                    claim_score=1.0,
                    claim_visible=np.zeros(info.shape, bool),
                ),  # fmt: skip
                "done with its mac": dataclasses.replace(last, seq=4, done=True),
                "no mac": dataclasses.replace(last, seq=4, mac=None),
                "a made-up mac": dataclasses.replace(last, seq=4, mac="0" * 64),
            },
            "r1": {
                "robot 0's request as robot 1": last,
                "robot 0's request as robot 1, next seq": dataclasses.replace(last, seq=4),
            },
        }
        for robot, tries in attacks.items():
            for what, request in tries.items():
                reply = _get(sniffer, robot_key(SNIFFED, robot, "step"), request.encode())
                assert isinstance(reply, ErrorReply), what
                assert "without this run's token's signature" in reply.message, what
        replayed = _get(sniffer, robot_key(SNIFFED, "r0", "step"), last.encode())
        assert isinstance(replayed, StepReply) and replayed.seq == 3  # the cached reply, as
        assert [tuple(p) for p in replayed.poses] == [
            v.scans[k].pose for k, v in enumerate(victims[3])
        ]
    finally:
        queryable.undeclare()
        sniffer.close()
    # the victims' run is unaffected: every step moves every robot as its planner asked
    for seq in (4, 5, 6):
        steps = _team_step(sources, seq, walks)
        for robot, step in enumerate(steps):
            assert step.scans[robot].pose == tuple(map(int, walks[robot][seq - 1][-1])), seq
            assert not step.finished and step.lost == ()
    assert worlds.processes[SNIFFED].poll() is None
    log = worlds.log_of(SNIFFED)
    assert "without this run's token's signature" in log and "Traceback" not in log
    assert "standing still" not in log and "refused motion" not in log


def _forged_replies(seq: int, truth: GroundTruth, far: tuple[int, int]) -> list[Message]:
    """What a rogue answers a step query of seq `seq` with: the team finished, the robot
    teleported to `far` (a true scan there), and a refusal."""
    world = truth.to_world("forged", 0.1)
    scan = Simulator(world, [far], DEFAULTS.sensor, DEFAULTS.motion).scan(0)
    one = {
        "stood_still": np.zeros(1, bool), "claim_state": np.zeros(1, np.uint8),
        "claim_goals": np.zeros((1, 2), np.int32), "claim_scores": np.zeros(1),
        "claim_visible": np.zeros((0, *world.shape), bool), "lost": np.zeros(1, bool),
    }  # fmt: skip
    no_scans = (
        np.zeros((0, 2), np.int32),
        np.zeros((0, 2500), np.uint16),
        np.zeros((0, 2500), bool),
    )
    return [
        StepReply(seq, True, *no_scans, **one),
        StepReply(
            seq,
            False,
            np.array([far], np.int32),
            scan.n_cells[None].astype(np.uint16),
            scan.hit[None],
            **one,
        ),  # fmt: skip
        ErrorReply("robot r0: refused by a rogue"),
    ]


@pytest.mark.parametrize("run", [FORGED, FORGED_PLAIN])
def test_forged_world_replies_are_dropped_and_a_held_query_delays_nothing(hub, worlds, run):
    """Rogues on the hub answer every step query of the run first with forged replies (the
    team finished, a teleport, a refusal) and hold others unanswered. With a run token the
    planner takes only replies carrying its world's MAC; without, the moves it checks
    refuse a finish it did not ask for and a jump it could not make. Either way the robot
    moves as asked, at the world's pace (a held query is not waited for)."""
    session = hub[0]
    info, truth = _fetch(session, run)
    start = tuple(map(int, info.starts[0]))
    far = tuple(map(int, np.argwhere(~truth.occupancy & truth.valid_space)[-1]))
    walk = random_walk(truth.occupancy, start, 4, 3, seed=4)
    rogue = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    held: list = []

    def forge(query) -> None:
        seq = StepRequest.decode(query.payload.to_bytes()).seq
        for forged in _forged_replies(seq, truth, far):
            query.reply(query.key_expr, forged.encode())

    def hold(query) -> None:
        held.append(query)  # never answered while the test runs

    queryables = [
        rogue.declare_queryable(robot_key(run, "r0", "step"), forge),
        rogue.declare_queryable(robot_key(run, "r0", "step"), hold),
    ]
    source = ZenohWorld(session, run, 0, run_token=TOKENS.get(run))
    try:
        time.sleep(0.5)  # the rogues' queryables are known to the hub
        source.fetch(timeout_s=10.0)
        (scan,) = source.initial()
        assert scan.pose == start
        for t, cells in enumerate(walk):
            began = time.monotonic()
            step = source.step(t, [Decision(0, cells)])
            took_s = time.monotonic() - began
            assert not step.finished and step.scans[0].pose == tuple(map(int, cells[-1])), t
            assert took_s < ServicesConfig().step_timeout_s, took_s  # not held to a timeout
        assert held  # the holder did get the queries
    finally:
        for queryable in queryables:
            queryable.undeclare()
        held.clear()
        rogue.close()
    assert worlds.processes[run].poll() is None


def test_sigint_stops_the_world_cleanly(hub, worlds):
    process = worlds.processes[SIGINT]
    process.send_signal(signal.SIGINT)
    assert process.wait(STOP_DEADLINE_S) == 0
    assert not _token_alive(hub[0], SIGINT)
    log = worlds.log_of(SIGINT)
    assert "stopped after serving 0 scans" in log and "Traceback" not in log


BAD_WORLD_FLAGS = [
    (["--world", "generated:x"], "bad generated seed 'x'"),
    (["--world", "{missing}"], "no such map directory"),
    (["--starts", "7"], "corners are 0-3"),
    (["--starts", "0,1"], "start cell (0, 1) is on a wall"),
    (["--robots", "2", "--starts", "0"], "names 1 starts for 2 robots"),
    (["--robots", "0"], "--robots must be at least 1"),
    (["--run", "predict"], "--run 'predict' must match"),
    (["--team", "2"], "unrecognized arguments: --team"),
    (["--set", "sensor.nope=1"], "override 'sensor.nope=1': unknown field 'nope'"),
    (["--set", "services.team_step_wait_s=soon"], "'soon' is not a valid float"),
    (["--set", "motion.cells_per_step"], "is not of the form section.field=value"),
    (["--set", "world.max_cells=100"], "cells (363 x 537), above the limit of 100:"),
]


@pytest.fixture(scope="module")
def bad_world_runs(tmp_path_factory) -> dict[tuple[str, ...], subprocess.CompletedProcess]:
    """`python -m services.world` with each of BAD_WORLD_FLAGS ({missing}: a folder that is
    not there), all run at once (each only parses and fails)."""
    missing = tmp_path_factory.mktemp("bad-world-flags") / "none"
    cases = []
    for case, _ in BAD_WORLD_FLAGS:
        flags = [f.format(missing=missing) for f in case]
        if "--run" not in flags:
            flags += ["--run", "bad_flags"]
        cases.append(["services.world", *flags, "--connect", "tcp/127.0.0.1:1"])
    runs = run_python_m(cases)
    return dict(zip((tuple(flags) for flags, _ in BAD_WORLD_FLAGS), runs, strict=True))


@pytest.mark.parametrize("flags, message", BAD_WORLD_FLAGS)
def test_bad_world_starts_and_flags_are_one_line_errors(flags, message, bad_world_runs):
    result = bad_world_runs[tuple(flags)]
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert sum(message in line for line in result.stderr.splitlines()) == 1


# ---------------------------------------------------------------------- the pure WorldServer


SMALL = ExplorationConfig(sensor=SensorConfig(n_rays=90, range_cells=40))
QUICK = ServicesConfig(team_step_wait_s=2.0)


@pytest.fixture(scope="module")
def world():
    return load_world(WORLD_SPEC)


def test_world_server_serves_fresh_steps_once_and_caches_retries(world):
    heard = []
    server = WorldServer(world, [0], SMALL, on_step=lambda *event: heard.append(event))
    start = server.starts[0]
    (cells,) = random_walk(world.occupancy, start, 1, 3, seed=1)
    first = server.answer_step(0, step_request(0))
    assert isinstance(first, StepReply) and tuple(first.poses[0]) == start
    assert server.answer_step(0, step_request(0, cells)) is first  # a retry: cached
    moved = server.answer_step(0, step_request(1, cells))
    assert tuple(moved.poses[0]) == tuple(map(int, cells[-1]))
    assert [(robot, seq) for robot, seq, _ in heard] == [(0, 0), (0, 1)]
    assert isinstance(heard[-1][2], ScanReply) and heard[-1][2].pose == tuple(moved.poses[0])
    assert server.served == 2 and server.seq == 2


def test_a_planner_that_finished_is_not_a_lost_robot(world, caplog):
    """A planner leaving after the run's last step is logged as finished (INFO); one leaving
    before is a lost robot (WARNING)."""
    config = dataclasses.replace(SMALL, steps=1)
    for seq, lost in ((2, False), (1, True)):
        server = WorldServer(world, [0], config)
        for k in range(seq):
            server.answer_step(0, step_request(k))
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="services.world"):
            server.planner_gone(0)
        (record,) = caplog.records
        assert ("is lost" in record.getMessage()) == lost, record.getMessage()
        assert record.levelno == (logging.WARNING if lost else logging.INFO)


@pytest.mark.parametrize(
    "robot, payload, match",
    [
        (0, step_request(1), "step seq 1 is out of order, at 0"),
        (0, None, "carries no payload"),
        (0, b"\x93garbage", "malformed step request"),
        (0, ErrorReply("x").encode(), "malformed step request"),
        (1, step_request(0), "robot 1 is not one of 0-0"),
        (-1, step_request(0), "robot -1 is not one of"),
    ],
)
def test_world_server_refuses_bad_requests_without_raising(world, robot, payload, match):
    server = WorldServer(world, [0], SMALL)
    reply = server.answer_step(robot, payload)
    assert isinstance(reply, ErrorReply) and match in reply.message
    assert "\n" not in reply.message and server.served == 0 and server.seq == 0
    assert tuple(server.simulator.poses[0]) == server.starts[0]


def test_a_refused_motion_leaves_the_robot_where_it_stands_and_the_run_goes_on(world, caplog):
    server = WorldServer(world, [0], SMALL)
    start = server.starts[0]
    server.answer_step(0, step_request(0))
    with caplog.at_level(logging.WARNING, logger="services.world"):
        stood = server.answer_step(0, step_request(1, [[0, 0]]))  # a wall, far away
    assert isinstance(stood, StepReply) and tuple(stood.poses[0]) == start
    assert "robot r0: refused motion of step 1" in caplog.text
    (cells,) = random_walk(world.occupancy, start, 1, 3, seed=3)
    moved = server.answer_step(0, step_request(2, cells))
    assert tuple(moved.poses[0]) == tuple(map(int, cells[-1])) and server.served == 3


MAC_RUN, MAC_TOKEN = "mac_test", "s3cret"


def _tampered() -> dict[str, bytes]:
    """Requests for robot 0 of MAC_RUN that a holder of the token did not sign so."""
    key = step_key(MAC_TOKEN, MAC_RUN)
    visible = np.zeros((5, 5), dtype=bool)
    plain = unsigned_request(0, [[3, 4]])
    claim = unsigned_request(0, [[3, 4]], claim=((2, 2), 1.5, visible))
    signed, claimed = plain.signed(key, MAC_RUN, 0), claim.signed(key, MAC_RUN, 0)
    other_cells = visible.copy()
    other_cells[1, 1] = True
    old = msgpack.unpackb(plain.encode())  # the token in clear, as requests carried it
    return {
        "no mac": plain.encode(),
        "a random mac": dataclasses.replace(plain, mac="ab" * 32).encode(),
        "signed with another token": plain.signed(step_key("wrong", MAC_RUN), MAC_RUN, 0).encode(),
        "signed for another run": plain.signed(step_key(MAC_TOKEN, "other"), "other", 0).encode(),
        "signed for robot 1": plain.signed(key, MAC_RUN, 1).encode(),
        "other cells": dataclasses.replace(signed, cells=np.array([[3, 5]], np.int32)).encode(),
        "no cells": dataclasses.replace(signed, cells=np.zeros((0, 2), np.int32)).encode(),
        "another seq": dataclasses.replace(signed, seq=1).encode(),
        "done": dataclasses.replace(signed, done=True).encode(),
        "claimed": dataclasses.replace(signed, claimed=True).encode(),
        "another claim goal": dataclasses.replace(claimed, claim_goal=(2, 3)).encode(),
        "another claim score": dataclasses.replace(claimed, claim_score=9.0).encode(),
        "other claimed cells": dataclasses.replace(claimed, claim_visible=other_cells).encode(),
        "the claim dropped": dataclasses.replace(claimed, claim_goal=None).encode(),
        "the token in clear": msgpack.packb({**old, "run_token": MAC_TOKEN}),
    }


@pytest.mark.parametrize("what", list(_tampered()))
def test_a_world_with_a_run_token_refuses_requests_not_signed_as_they_are(world, what):
    """The MAC binds the run, the robot and everything the request asks: a MAC moved to
    another request, robot or run, made with another token, or none, moves nothing."""
    server = WorldServer(world, [0], SMALL, run_token=MAC_TOKEN, run=MAC_RUN)
    reply = server.answer_step(0, _tampered()[what])
    assert isinstance(reply, ErrorReply), what
    wanted = "malformed step request" if what == "the token in clear" else "run's token's signature"
    assert wanted in reply.message and "\n" not in reply.message
    assert server.served == 0 and server.seq == 0  # nothing moved, seq untouched
    key = step_key(MAC_TOKEN, MAC_RUN)
    good = unsigned_request(0).signed(key, MAC_RUN, 0)
    assert isinstance(server.answer_step(0, good.encode()), StepReply)
    assert server.answer_step(0, good.encode()).seq == 0  # sent again: the cached reply


def test_a_step_mac_is_the_documented_hmac_and_a_world_without_a_run_refuses_a_token(world):
    request = unsigned_request(4, [[1, 2]], claim=((3, 4), -np.inf, np.eye(3, dtype=bool)))
    key = step_key("tok", "run-1")
    assert key == hmac.new(b"tok", b"mapex step key v1|run-1", hashlib.sha256).digest()
    message = b"".join(request.signed_bytes("run-1", 2))

    def u64(*values) -> bytes:
        return b"".join(value.to_bytes(8, "little") for value in values)

    documented = (  # docs/protocol.md, byte by byte
        u64(21) + b"mapex step request v1" + u64(5) + b"run-1" + u64(2, 4) + b"\x00\x01"
        + u64(8) + np.array([1, 2], "<i4").tobytes()
        + b"\x01" + u64(3, 4) + np.array(-np.inf, "<f8").tobytes() + u64(3, 3)
        + u64(9) + np.eye(3, dtype=np.uint8).tobytes()
    )  # fmt: skip
    assert message == documented
    unclaimed = b"".join(unsigned_request(0).signed_bytes("r", 0))
    no_claim = u64(0, 0) + b"\x00\x00" + u64(0) + b"\x00"  # robot, seq, flags, no cells, goal
    assert unclaimed == u64(21) + b"mapex step request v1" + u64(1) + b"r" + no_claim
    mac = hmac.new(key, message, hashlib.sha256).hexdigest()
    signed = request.signed(key, "run-1", 2)
    assert signed.mac == mac and signed.signed_by(key, "run-1", 2)
    assert StepRequest.decode(signed.encode()).signed_by(key, "run-1", 2)  # survives the wire
    assert not signed.signed_by(key, "run-1", 1) and not signed.signed_by(key, "run-12", 2)
    with pytest.raises(ValueError, match="run id"):
        WorldServer(world, [0], SMALL, run_token="tok")


def test_world_server_knows_its_robots_starts_world_and_settings(world):
    server = WorldServer(world, [3, 1], SMALL)
    corners = start_poses(world, SMALL.world.start_clearance_cells)
    assert server.starts == [corners[3], corners[1]] and server.n_robots == 2
    info = server.world_info()
    np.testing.assert_array_equal(info.starts, [corners[3], corners[1]])
    assert info.settings() == {"n_rays": 90, "range_cells": 40, "cells_per_step": 3}
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


# ------------------------------------------------------ a team in lockstep (threads = planners)


TEAM_RUN, TEAM_TOKEN = "team_test", "tok"


@pytest.fixture
def team():
    team_world = load_world("generated:0")
    cells = team_start_cells(team_world, [0], 2, SMALL)
    return WorldServer(team_world, cells, SMALL, run_token=TEAM_TOKEN, services=QUICK, run=TEAM_RUN)


def team_request(seq: int, cells=(), done=False, claim=None, robot=0, token=TEAM_TOKEN) -> bytes:
    return step_request(seq, cells, done, claim, token, TEAM_RUN, robot)


def together(server, payloads: dict[int, bytes | None]) -> dict[int, object]:
    """Each robot's request sent from a thread of its own, as planners do; the replies."""
    replies: dict[int, object] = {}
    threads = [
        threading.Thread(target=lambda r=r, p=p: replies.update({r: server.answer_step(r, p)}))
        for r, p in payloads.items()
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(5.0)
    return replies


def test_every_robot_gets_every_scan_and_claim_of_the_step(team):
    first = together(team, {0: team_request(0), 1: team_request(0, robot=1)})
    assert first[0] is first[1] and isinstance(first[0], StepReply)
    np.testing.assert_array_equal(first[0].poses, team.starts)
    start = team.starts[0]
    step = (start[0], start[1] + 1)
    visible = np.zeros(team.world.shape, dtype=bool)
    visible[5, 5] = True
    second = together(team, {0: team_request(1, [step], claim=((30, 30), 2.5, visible)),
                             1: team_request(1, robot=1)})  # fmt: skip
    reply = second[0]
    assert second[1] is reply
    assert tuple(reply.poses[0]) == step and tuple(reply.poses[1]) == tuple(team.starts[1])
    assert list(reply.claim_state) == [1, 0] and reply.claim_scores[0] == 2.5
    assert len(reply.claim_visible) == 1 and reply.visible_of(0)[5, 5]  # new claims only
    assert not reply.stood_still.any()
    assert team.answer_step(1, team_request(1, robot=1)) is reply  # a retry gets the same reply
    assert team.served == 4  # two robots, two steps: a retry scans nothing


def test_a_step_waits_for_every_robot_and_the_late_one_gets_the_step_it_missed(team):
    together(team, {0: team_request(0), 1: team_request(0, robot=1)})
    start = team.starts[0]
    began = time.monotonic()
    (reply,) = together(team, {0: team_request(1, [(start[0], start[1] + 1)])}).values()
    assert time.monotonic() - began >= QUICK.team_step_wait_s - 0.05  # it waited for r1
    assert list(reply.stood_still) == [False, True]
    late_cells = [(team.starts[1][0] + 1, team.starts[1][1])]
    late = team.answer_step(1, team_request(1, late_cells, robot=1))
    assert late is reply and tuple(reply.poses[1]) == tuple(team.starts[1])  # not applied
    replies = together(team, {0: team_request(2), 1: team_request(2, robot=1)})  # in step again
    assert replies[0] is replies[1] and not replies[0].stood_still.any()


def test_a_team_with_nothing_left_is_finished_without_a_step(team):
    together(team, {0: team_request(0), 1: team_request(0, robot=1)})
    one_done = together(team, {0: team_request(1, done=True), 1: team_request(1, robot=1)})
    assert not one_done[0].finished and len(one_done[0].poses) == 2  # the other goes on
    served = team.served
    both_done = {0: team_request(2, done=True), 1: team_request(2, done=True, robot=1)}
    replies = together(team, both_done)
    assert replies[0].finished and len(replies[0].poses) == 0 and team.served == served


def test_a_robot_alone_with_nothing_left_is_finished(world):
    server = WorldServer(world, [0], SMALL)
    assert not server.answer_step(0, step_request(0, done=True)).finished  # seq 0: scans
    reply = server.answer_step(0, step_request(1, done=True))
    assert reply.finished and len(reply.poses) == 0 and server.served == 1


def test_team_steps_without_the_token_or_out_of_order_are_refused(team):
    unsigned = team.answer_step(0, team_request(0, token="x"))
    assert "without this run's token's signature" in unsigned.message
    reply = team.answer_step(0, team_request(3))
    assert isinstance(reply, ErrorReply) and "out of order" in reply.message
    assert "malformed step request" in team.answer_step(0, b"\x00junk").message
    assert team.seq == 0 and team.served == 0


def test_a_lost_robot_is_not_waited_for_and_its_claim_expires(team):
    together(team, {0: team_request(0), 1: team_request(0, robot=1)})
    visible = np.zeros(team.world.shape, dtype=bool)
    claim = team_request(1, claim=((30, 30), 1.0, visible), robot=1)
    together(team, {0: team_request(1), 1: claim})
    team.planner_gone(1)
    began = time.monotonic()
    (reply,) = together(team, {0: team_request(2)}).values()
    assert time.monotonic() - began < QUICK.team_step_wait_s  # not waited for
    assert list(reply.lost) == [False, True] and list(reply.stood_still) == [False, True]
    assert list(reply.claim_state) == [0, 2]  # robot 1's claim is withdrawn, once
    (after,) = together(team, {0: team_request(3, done=True)}).values()
    assert list(after.claim_state) == [0, 0] and after.finished  # the robots left are done


def test_a_planner_whose_liveliness_token_goes_makes_its_robot_lost(hub, team):
    planners = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    watcher = team.watch_planners(hub[0], "lost_test")
    try:
        tokens = [
            planners.liveliness().declare_token(alive_planner_key(run, robot))
            for run, robot in (("lost_test", "r0"), ("lost_test", "r1"), ("other", "r0"))
        ]
        time.sleep(0.5)  # the tokens arrive; a token that appears loses nobody
        assert team.lost == set()
        tokens[2].undeclare()  # another run's robot 0
        tokens[1].undeclare()
        until(lambda: team.lost == {1}, "robot r1 to be lost")
        time.sleep(0.3)
        assert team.lost == {1}
        tokens[0].undeclare()
        until(lambda: team.lost == {0, 1}, "robot r0 to be lost")
    finally:
        watcher.undeclare()
        planners.close()


# ------------------------------------------------------------- the planner's side: ZenohWorld


def test_a_planner_s_zenoh_world_gets_what_an_in_process_simulator_gives(hub, world):
    server = WorldServer(world, [0], SMALL)
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(hub[0], server, "client_test", stop))
    thread.start()
    session = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    try:
        source = ZenohWorld(session, "client_test", 0)
        info, fetched = source.fetch(timeout_s=10.0)
        assert info.settings() == {"n_rays": 90, "range_cells": 40, "cells_per_step": 3}
        np.testing.assert_array_equal(fetched.occupancy, world.occupancy)
        local = Simulator(world, server.starts, SMALL.sensor, SMALL.motion)
        (scan,) = source.initial()
        _assert_same_scan(scan, local.scan(0))
        (cells,) = random_walk(world.occupancy, server.starts[0], 1, 3, seed=4)
        visible = np.zeros(world.shape, dtype=bool)
        visible[3, 4] = True
        claim = Claim(0, 0, (30, 40), -np.inf, visible)  # a last-resort claim travels too
        step = source.step(0, [Decision(0, cells, True, claim)])
        (scan,) = step.scans
        _assert_same_scan(scan, local.step(0, cells))
        (got,) = step.claims.values()
        assert (got.robot, got.t, got.goal, got.score) == (0, 0, (30, 40), -np.inf)
        np.testing.assert_array_equal(got.visible, visible)
        assert not step.finished and step.lost == ()
        assert source.step(1, [Decision(0, np.zeros((0, 2)), True, None)]).claims == {0: None}
        done = source.step(2, [Decision(0, None)])
        assert done.finished and done.scans == []
    finally:
        session.close()
        stop.set()
        thread.join(10.0)
    assert server.served == 3


def test_a_gone_world_is_asked_again_with_back_off_for_the_whole_wait():
    """A step query nobody serves returns at once: the planner keeps asking, with growing
    pauses, until step_retries x (step_timeout_s + team_step_wait_s) has passed, and says
    so honestly."""
    services = ServicesConfig(
        step_timeout_s=0.3, team_step_wait_s=0.2, step_retries=2, step_retry_pause_s=(0.05, 0.2)
    )
    session = open_session(zenoh_config("peer", [], [f"tcp/127.0.0.1:{free_loopback_port()}"]))
    try:
        began = time.monotonic()
        with pytest.raises(WorldUnavailableError) as info:
            ZenohWorld(session, "nobody", 0, services).initial()
        elapsed_s = time.monotonic() - began
    finally:
        session.close()
    found = re.search(r"did not answer step 0 in ([\d.]+) s \((\d+) queries\)", str(info.value))
    assert found is not None, str(info.value)
    assert 0.8 <= float(found.group(1)) <= elapsed_s + 0.05 <= 5.0
    assert int(found.group(2)) >= 4  # asked again and again, not three times in a few ms
