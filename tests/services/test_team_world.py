"""services.team_world: the team's world clock, without Zenoh (threads stand for planners)."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from mapex.config import ExplorationConfig
from mapex.team.starts import team_start_cells
from mapex.worlds import load_world
from services.codec import ProtocolError
from services.config import ServicesConfig
from services.messages import ErrorReply, TeamScanReply, TeamStepRequest
from services.team_world import TeamWorldServer

CONFIG = ExplorationConfig()
QUICK = ServicesConfig(team_step_wait_s=2.0)


@pytest.fixture
def server():
    world = load_world("generated:0")
    cells = team_start_cells(world, [0], 2, CONFIG)
    return TeamWorldServer(world, cells, CONFIG, run_token="tok", services=QUICK)


def request(seq: int, cells=(), done: bool = False, claim=None, token: str = "tok") -> bytes:
    goal, score, visible = claim if claim is not None else (None, None, None)
    cells = np.asarray(cells, dtype=np.int32).reshape(-1, 2)
    return TeamStepRequest(
        seq, cells, done, claim is not None, goal, score, visible, token
    ).encode()


def together(server, payloads: dict[int, bytes]) -> dict[int, object]:
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


def test_every_robot_gets_every_scan_and_claim_of_the_step(server):
    first = together(server, {0: request(0), 1: request(0)})
    assert first[0] is first[1] and isinstance(first[0], TeamScanReply)
    np.testing.assert_array_equal(first[0].poses, server.starts)
    start = server.starts[0]
    step = (start[0], start[1] + 1)
    visible = np.zeros(server.world.shape, dtype=bool)
    visible[5, 5] = True
    second = together(server, {0: request(1, [step], claim=((30, 30), 2.5, visible)),
                               1: request(1)})  # fmt: skip
    reply = second[0]
    assert tuple(reply.poses[0]) == step and tuple(reply.poses[1]) == tuple(server.starts[1])
    assert list(reply.claim_state) == [1, 0] and reply.claim_scores[0] == 2.5
    assert len(reply.claim_visible) == 1 and reply.visible_of(0)[5, 5]  # new claims only
    assert not reply.stood_still.any()
    assert server.answer_step(1, request(1)) is reply  # a retry gets the same reply


def test_a_late_robot_stands_still_and_gets_the_step_it_missed(server):
    together(server, {0: request(0), 1: request(0)})
    start = server.starts[0]
    (reply,) = together(server, {0: request(1, [(start[0], start[1] + 1)])}).values()
    assert list(reply.stood_still) == [False, True]
    late = server.answer_step(1, request(1, [(server.starts[1][0] + 1, server.starts[1][1])]))
    assert late is reply and tuple(reply.poses[1]) == tuple(server.starts[1])  # not applied


def test_a_team_with_nothing_left_is_finished_without_a_step(server):
    together(server, {0: request(0), 1: request(0)})
    replies = together(server, {0: request(1, done=True), 1: request(1, done=True)})
    assert replies[0].finished and len(replies[0].poses) == 0


def test_steps_without_the_token_or_out_of_order_are_refused(server):
    assert "without this run's token" in server.answer_step(0, request(0, token="x")).message
    reply = server.answer_step(0, request(3))
    assert isinstance(reply, ErrorReply) and "out of order" in reply.message
    assert "malformed team step request" in server.answer_step(0, b"\x00junk").message


def test_a_lost_robot_is_not_waited_for_and_its_claim_expires(server):
    together(server, {0: request(0), 1: request(0)})
    visible = np.zeros(server.world.shape, dtype=bool)
    together(server, {0: request(1), 1: request(1, claim=((30, 30), 1.0, visible))})
    server.planner_gone(1)
    (reply,) = together(server, {0: request(2)}).values()
    assert list(reply.lost) == [False, True] and list(reply.stood_still) == [False, True]
    assert list(reply.claim_state) == [0, 2]  # robot 1's claim is withdrawn, once
    (after,) = together(server, {0: request(3, done=True)}).values()
    assert list(after.claim_state) == [0, 0] and after.finished  # the robots left are done


def test_a_last_resort_claim_scored_minus_infinity_goes_through():
    """nearest_team rules out frontiers near a teammate's goal with -inf and still takes one
    when nothing else is left: that claim travels; NaN and +inf scores are refused."""
    visible = np.zeros((4, 5), dtype=bool)
    payload = request(1, claim=((2, 3), -math.inf, visible))
    assert TeamStepRequest.decode(payload).claim_score == -math.inf
    for bad in (math.nan, math.inf):
        with pytest.raises(ProtocolError, match="claim_score"):
            request(1, claim=((2, 3), bad, visible))


def test_claimed_cells_travel_for_new_claims_only_in_robot_order():
    """A reply carries one claimed-cells map per new claim: the second robot's claim is the
    first row when the first robot made none; a reply whose rows do not match is refused."""
    shape = (6, 7)
    state = np.array([0, 1, 2], dtype=np.uint8)
    visible = np.zeros((1, *shape), dtype=bool)
    visible[0, 2, 3] = True
    reply = TeamScanReply(
        3, False, np.zeros((0, 2), np.int32), np.zeros((0, 5), np.uint16),
        np.zeros((0, 5), bool), np.zeros(3, bool), state, np.zeros((3, 2), np.int32),
        np.array([0.0, 1.5, 0.0]), visible, np.zeros(3, bool),
    )  # fmt: skip
    decoded = TeamScanReply.decode(reply.encode())
    assert decoded.visible_of(1)[2, 3] and decoded.visible_of(1).sum() == 1
    with pytest.raises(ProtocolError, match="one row per new claim"):
        TeamScanReply(
            3, False, np.zeros((0, 2), np.int32), np.zeros((0, 5), np.uint16),
            np.zeros((0, 5), bool), np.zeros(3, bool), state, np.zeros((3, 2), np.int32),
            np.zeros(3), np.zeros((3, *shape), bool), np.zeros(3, bool),
        )  # fmt: skip
