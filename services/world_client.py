"""The planner's side of the world process: a `mapex.episode.StepSource` over Zenoh.

A step is a query on `mapex/@v1/<run>/<robot>/step` carrying the robot's sequence number;
a query that gets no reply is sent again with the same number (the world answers a repeat
with its cached reply and does not move the robot twice). The world's name, size, settings
and ground truth come from its `world_info` and `ground_truth` queryables, asked until they
answer (docs/protocol.md).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import zenoh

from mapex.episode import WorldStep
from mapex.methods.claims import Claim
from mapex.sensor import Scan
from mapex.team.team import Decision
from mapex.worlds.base import World
from services.codec import DEFAULT_SERVICES, ProtocolError
from services.config import ServicesConfig
from services.keys import robot_id, robot_key, run_key
from services.messages import (
    CLAIM_MADE,
    CLAIM_WITHDRAWN,
    ErrorReply,
    GroundTruth,
    Message,
    StepReply,
    StepRequest,
    WorldInfo,
    decode_message,
)

_RETRY_PAUSE_S = 0.2  # between start-up queries for the world's keys

log = logging.getLogger("services.world_client")


class WorldUnavailableError(RuntimeError):
    """The world process did not answer (in time, or at all); the message is one line."""


class StepRefusedError(RuntimeError):
    """The world refused a step (bad motion, out-of-order seq); the message is one line."""


class ZenohWorld:
    """Robot `robot` of a run, moved and scanned by the world process reachable through
    `session`: it sends this robot's decision of each step and gets every robot's scan and
    the claims made at it back."""

    def __init__(
        self,
        session: zenoh.Session,
        run: str,
        robot: int,
        services: ServicesConfig = DEFAULT_SERVICES,
        run_token: str | None = None,
    ) -> None:
        self.session = session
        self.run = run
        self.robot = robot
        self.services = services
        self.run_token = run_token  # carried by every step (the world may require it)
        self.key = robot_key(run, robot_id(robot), "step")

    def fetch(self, timeout_s: float | None = None) -> tuple[WorldInfo, World]:
        """The world's info and its ground truth as a `World`, waiting for the world to serve."""
        timeout_s = self.services.world_wait_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        info = self._wait_for(run_key(self.run, "world_info"), WorldInfo, deadline)
        truth = self._wait_for(run_key(self.run, "ground_truth"), GroundTruth, deadline)
        if truth.occupancy.shape != info.shape:
            raise WorldUnavailableError(
                f"run {self.run}: ground truth {truth.occupancy.shape} != world size {info.shape}"
            )
        return info, truth.to_world(info.name, info.resolution_m)

    def initial(self) -> list[Scan]:
        """Every robot's scan where it stands (seq 0)."""
        return self._step(0, Decision(self.robot, np.zeros((0, 2), dtype=np.int32))).scans

    def step(self, t: int, decisions: list[Decision]) -> WorldStep:
        """Send this robot's decision of step t; the team's scans and claims of it."""
        (mine,) = [d for d in decisions if d.robot == self.robot]
        return self._step(t + 1, mine)

    def _step(self, seq: int, decision: Decision) -> WorldStep:
        claim = decision.claim
        motion = np.zeros((0, 2)) if decision.motion is None else decision.motion
        cells = np.asarray(motion, dtype=np.int32).reshape(-1, 2)
        done = decision.motion is None and seq > 0  # seq 0 asks for the initial scans
        request = StepRequest(
            seq, cells, done, decision.claimed, None if claim is None else claim.goal,
            None if claim is None else claim.score, None if claim is None else claim.visible,
            self.run_token,
        )  # fmt: skip
        wait_s = self.services.step_timeout_s + self.services.team_step_wait_s
        reply = self._request(self.key, request.encode(self.services), seq, StepReply, wait_s)
        return _world_step_of(reply, max(seq - 1, 0))

    def _request(
        self, key: str, payload: bytes, seq: int, kind: type[Message], timeout_s: float
    ) -> Message:
        """The world's reply of type `kind` to step query `seq` on `key`, asked again with
        back-off while unanswered; StepRefusedError or WorldUnavailableError (one line)."""
        began = time.monotonic()
        deadline = began + self.services.step_retries * timeout_s
        pause, longest_pause = self.services.step_retry_pause_s
        attempt = 0
        while True:
            attempt += 1
            wait_s = max(min(timeout_s, deadline - time.monotonic()), 0.1)
            message = self._ask(key, payload, (kind, ErrorReply), wait_s)
            if isinstance(message, ErrorReply):
                raise StepRefusedError(f"{key}: {message.message}")
            if message is not None:
                return message
            if time.monotonic() + pause >= deadline:
                break
            log.warning("%s: no reply to step %d (query %d), asking again", key, seq, attempt)
            time.sleep(pause)
            pause = min(2 * pause, longest_pause)
        raise WorldUnavailableError(
            f"{key}: the world did not answer step {seq} in "
            f"{time.monotonic() - began:.1f} s ({attempt} queries)"
        )

    def _wait_for(self, key: str, kind: type[Message], deadline: float) -> Message:
        while True:
            message = self._ask(key, b"", (kind,), timeout_s=1.0)
            if message is not None:
                return message
            if time.monotonic() >= deadline:
                raise WorldUnavailableError(f"no world serves run {self.run!r} ({key})")
            time.sleep(_RETRY_PAUSE_S)

    def _ask(
        self, key: str, payload: bytes, kinds: tuple[type[Message], ...], timeout_s: float
    ) -> Message | None:
        """The first decodable reply of the expected kinds to one query, or None."""
        for reply in self.session.get(key, payload=payload or None, timeout=timeout_s):
            sample = reply.ok if reply.ok is not None else reply.err
            try:
                return decode_message(sample.payload.to_bytes(), kinds, self.services)
            except ProtocolError as error:
                log.warning("%s: dropped a reply: %s", key, error)
        return None


def _world_step_of(reply: StepReply, t: int) -> WorldStep:
    """The `WorldStep` a step reply carries (claims made at step t)."""
    scans = [
        Scan((int(pose[0]), int(pose[1])), n_cells.copy(), hit.copy())
        for pose, n_cells, hit in zip(reply.poses, reply.n_cells, reply.hit, strict=True)
    ]
    claims: dict[int, Claim | None] = {}
    for robot, state in enumerate(reply.claim_state):
        if state == CLAIM_WITHDRAWN:
            claims[robot] = None
        elif state == CLAIM_MADE:
            goal = (int(reply.claim_goals[robot][0]), int(reply.claim_goals[robot][1]))
            score, visible = float(reply.claim_scores[robot]), reply.visible_of(robot).copy()
            claims[robot] = Claim(robot, t, goal, score, visible)
    lost = tuple(int(robot) for robot in np.flatnonzero(reply.lost))
    return WorldStep(scans, claims, reply.finished, lost)
