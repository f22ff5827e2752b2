"""The team's world: the clock of a team of robots sharing one world (docs/algorithms.md#teams).

`TeamWorldServer` answers the step queries of a team's planners like `WorldServer` answers
one robot's, but in lockstep: a `team_step_request` of seq s waits until every robot's
request of seq s is in (or `ServicesConfig.team_step_wait_s` has passed since the first
arrived: a late robot stands still for that step), then every robot moves, and every
planner gets the same `team_scan_reply`: all robots' scans and the claims made at s. A
request for an earlier seq (a retry, or a robot that was late) gets that step's reply again
(the last few are kept); motions of late requests are not applied. A robot whose planner's
liveliness token goes is lost: nobody waits for it any more, it stands still, and its claim
is withdrawn. The reply says `finished` (and nobody moves) when every robot left had
nothing left to explore.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict

import numpy as np
import zenoh

from mapex.config import ExplorationConfig
from mapex.simulator import MotionError
from mapex.worlds import StartSpec, World
from services.codec import DEFAULT_SERVICES, ProtocolError
from services.config import ServicesConfig
from services.keys import (
    ROBOT_ID_PREFIX,
    AliveKey,
    alive_planner_pattern,
    parse_key,
    robot_id,
)
from services.messages import (
    CLAIM_MADE,
    CLAIM_WITHDRAWN,
    ErrorReply,
    ScanReply,
    TeamScanReply,
    TeamStepRequest,
)
from services.world import DEFAULT_EXPLORATION, StepListener, WorldServer

log = logging.getLogger("services.team_world")

KEPT_REPLIES = 4  # steps whose reply is kept for late requests and retries


class TeamWorldServer(WorldServer):
    """`WorldServer` for a team: steps are collected and answered in lockstep (module doc)."""

    def __init__(
        self,
        world: World,
        starts: list[StartSpec],
        config: ExplorationConfig = DEFAULT_EXPLORATION,
        on_step: StepListener | None = None,
        run_token: str | None = None,
        services: ServicesConfig = DEFAULT_SERVICES,
    ) -> None:
        super().__init__(world, starts, config, on_step, run_token)
        self.services = services
        self.seq = 0  # the step being collected (0: the initial scans)
        self._requests: dict[int, TeamStepRequest] = {}
        self._first_arrival: float | None = None
        self._replies: OrderedDict[int, TeamScanReply] = OrderedDict()
        self._clock = threading.Condition()
        self.lost: set[int] = set()
        self._announced: set[int] = set()  # lost robots whose claim was withdrawn

    def watch_planners(self, session: zenoh.Session, run: str) -> zenoh.LivelinessSubscriber:
        """Mark a robot lost when its planner's liveliness token goes (undeclare the
        returned subscriber when done)."""
        return session.liveliness().declare_subscriber(
            alive_planner_pattern(run), self._on_planner_token, history=True
        )

    def planner_gone(self, robot: int) -> None:
        """Robot `robot`'s planner is gone: stop waiting for it."""
        with self._clock:
            if robot not in self.lost:
                log.warning("robot %s is lost: its planner is gone", robot_id(robot))
                self.lost.add(robot)
                self._clock.notify_all()

    def _on_planner_token(self, sample: zenoh.Sample) -> None:
        try:
            key = parse_key(str(sample.key_expr))
        except ProtocolError as error:
            log.warning("ignored a planner token: %s", error)
            return
        robot = _robot_index(key.robot) if isinstance(key, AliveKey) else None
        gone = sample.kind == zenoh.SampleKind.DELETE
        if gone and robot is not None and 0 <= robot < self.n_robots:
            self.planner_gone(robot)

    request_type = TeamStepRequest
    request_name = "team step request"

    def _answer(self, robot: int, request: TeamStepRequest) -> TeamScanReply | ErrorReply:
        """The team reply for robot `robot`'s request, once its step is served."""
        with self._clock:
            return self._wait_for_step(robot, request)

    def _wait_for_step(self, robot: int, request: TeamStepRequest) -> TeamScanReply | ErrorReply:
        if request.seq in self._replies:  # a retry, or a robot that was late
            return self._replies[request.seq]
        if request.seq != self.seq:
            return self._refuse(robot, f"step seq {request.seq} is out of order, at {self.seq}")
        self._requests[robot] = request
        if self._first_arrival is None:
            self._first_arrival = time.monotonic()
        deadline = self._first_arrival + self.services.team_step_wait_s
        while request.seq not in self._replies:
            remaining = deadline - time.monotonic()
            awaited = set(range(self.n_robots)) - self.lost
            if awaited <= self._requests.keys() or remaining <= 0:
                self._serve()
            else:
                self._clock.wait(remaining)
        return self._replies[request.seq]

    def _serve(self) -> None:
        """Move every robot (late ones stand still), then publish and cache the reply."""
        seq, requests = self.seq, self._requests
        late = [robot for robot in range(self.n_robots) if robot not in requests]
        slow = [robot for robot in late if robot not in self.lost]
        if slow:
            names = ", ".join(robot_id(robot) for robot in slow)
            log.warning("step %d: no request from %s in time: standing still", seq, names)
        finished = seq > 0 and not slow and all(r.done for r in requests.values())
        scans = []
        if not finished:
            scans = [self._move(robot, seq, requests.get(robot)) for robot in range(self.n_robots)]
        self._replies[seq] = self._team_reply(seq, finished, scans, requests, late)
        while len(self._replies) > KEPT_REPLIES:
            self._replies.popitem(last=False)
        self.seq, self._requests, self._first_arrival = seq + 1, {}, None
        self._clock.notify_all()

    def _move(self, robot: int, seq: int, request: TeamStepRequest | None) -> ScanReply:
        cells = np.zeros((0, 2), dtype=np.int32) if request is None else request.cells
        try:
            scan = self.simulator.step(robot, cells)
        except MotionError as error:
            log.warning("robot %s: refused motion of step %d: %s", robot_id(robot), seq, error)
            scan = self.simulator.scan(robot)
        reply = ScanReply.from_scan(scan)
        self.served += 1
        if self.on_step is not None:
            self.on_step(robot, seq, reply)
        return reply

    def _team_reply(
        self,
        seq: int,
        finished: bool,
        scans: list[ScanReply],
        requests: dict[int, TeamStepRequest],
        late: list[int],
    ) -> TeamScanReply:
        n, shape, rays = self.n_robots, self.world.shape, self.simulator.sensor.n_rays
        state = np.zeros(n, dtype=np.uint8)
        goals = np.zeros((n, 2), dtype=np.int32)
        scores = np.zeros(n, dtype=np.float64)
        for robot, request in requests.items():
            if not request.claimed:
                continue
            state[robot] = CLAIM_WITHDRAWN if request.claim_goal is None else CLAIM_MADE
            if request.claim_goal is not None:
                goals[robot], scores[robot] = request.claim_goal, request.claim_score
        for robot in sorted(self.lost - self._announced):  # its claim expires
            state[robot] = CLAIM_WITHDRAWN
            self._announced.add(robot)
        made = np.flatnonzero(state == CLAIM_MADE)  # the claimed cells of each, robot order
        visible = np.array([requests[r].claim_visible for r in made], dtype=bool)
        stood = np.zeros(n, dtype=bool)
        stood[late] = True
        lost = np.zeros(n, dtype=bool)
        lost[sorted(self.lost)] = True
        return TeamScanReply(
            seq, finished,
            np.array([s.pose for s in scans], dtype=np.int32).reshape(-1, 2),
            np.array([s.n_cells for s in scans], dtype=np.uint16).reshape(len(scans), rays),
            np.array([s.hit for s in scans], dtype=bool).reshape(len(scans), rays),
            stood, state, goals, scores,
            visible.reshape(len(made), *shape), lost,
        )  # fmt: skip


def _robot_index(robot: str | None) -> int | None:
    """The index of robot id `r<k>`, or None."""
    if robot is None or not robot.startswith(ROBOT_ID_PREFIX) or not robot[1:].isdigit():
        return None
    return int(robot[1:])
