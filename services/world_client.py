"""The planner's side of the world process: a `mapex.episode.StepSource` over Zenoh.

A step is a query on `mapex/@v1/<run>/<robot>/step` carrying the robot's sequence number;
a query that gets no reply is sent again with the same number (the world answers a repeat
with its cached reply and does not move the robot twice). In a run with a token, every
request carries its MAC under the run's step key instead of the token. The world's name,
size, settings and ground truth come from its `world_info` and `ground_truth` queryables,
asked until they answer (docs/protocol.md). A step reply is checked against them (robots,
rays, poses and scans, claims) before anything uses it: a world that answers garbage or
an invalid step is one line, `WorldUnavailableError`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np
import zenoh

from mapex.config import ConfigError, SensorConfig
from mapex.episode import WorldStep
from mapex.methods.claims import Claim
from mapex.sensor import Scan, cast_scan
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
    map_message_bytes,
    step_key,
    world_reply_signed,
)

_RETRY_PAUSE_S = 0.2  # between start-up queries for the world's keys
_ZENOH_TIMEOUT = b"Timeout"  # the error payload Zenoh ends a timed-out query with

log = logging.getLogger("services.world_client")


class WorldUnavailableError(RuntimeError):
    """The world process did not answer (in time, or at all); the message is one line."""


class StepRefusedError(RuntimeError):
    """The world refused a step (bad motion, out-of-order seq); the message is one line."""


class ZenohWorld:
    """Robot `robot` of a run, moved and scanned by the world process reachable through
    `session`: it sends this robot's decision of each step and gets every robot's scan and
    the claims made at it back. With `run_token` every step is signed with the run's step
    key (`services.messages.step_key`); the token itself is not kept nor sent. After `fetch`
    every step reply is checked against the world it described."""

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
        self._step_key = None if run_token is None else step_key(run_token, run)
        self.key = robot_key(run, robot_id(robot), "step")
        self.info: WorldInfo | None = None  # set by fetch: what step replies are checked by
        self.world: World | None = None
        self._sensor: SensorConfig | None = None  # the world's sensor, when it said it
        self._poses: np.ndarray | None = None  # every robot's cell after the last step

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
        if info.n_rays is not None and info.range_cells is not None:
            try:
                self._sensor = SensorConfig(info.n_rays, info.range_cells)
            except ConfigError as error:
                raise WorldUnavailableError(f"run {self.run}: world_info: {error}") from None
        self.info, self.world = info, truth.to_world(info.name, info.resolution_m)
        return info, self.world

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
        )  # fmt: skip
        if self._step_key is not None:
            request = request.signed(self._step_key, self.run, self.robot)
        wait_s = self.services.step_timeout_s + self.services.team_step_wait_s
        reply = self._request(self.key, request.encode(self.services), request, wait_s)
        if not reply.finished:
            self._poses = reply.poses.copy()
        return _world_step_of(reply, max(seq - 1, 0))

    def _request(
        self, key: str, payload: bytes, request: StepRequest, timeout_s: float
    ) -> StepReply:
        """The world's valid reply to step query `request` on `key`, asked again with
        back-off while unanswered (a query that timed out too); StepRefusedError or
        WorldUnavailableError (one line)."""
        began, seq = time.monotonic(), request.seq
        deadline = began + self.services.step_retries * timeout_s
        pause, longest_pause = self.services.step_retry_pause_s
        attempt, check = 0, self._step_check(request)
        while True:
            attempt += 1
            wait_s = max(min(timeout_s, deadline - time.monotonic()), 0.1)
            message = self._ask(key, payload, (StepReply, ErrorReply), wait_s, check)
            if isinstance(message, ErrorReply):
                raise StepRefusedError(f"{key}: {message.message}")
            if isinstance(message, StepReply):
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
        self,
        key: str,
        payload: bytes,
        kinds: tuple[type[Message], ...],
        timeout_s: float,
        check: Callable[[Message], str | None] | None = None,
    ) -> Message | None:
        """The first valid reply of the expected kinds to one query (an ErrorReply needs no
        `check`), or None when none came (Zenoh's own end of a timed-out query is none).
        Every queryable on `key` is asked and each reply taken as it comes, so an answer
        held back elsewhere delays nothing. In a run with a token, a reply that does not
        carry the world's MAC of it (`world_reply_signed`) is not the world's: dropped;
        without a token, an error reply is returned only if no valid reply came.
        With `check`, a query whose world replies were all invalid (undecodable, of another
        kind, or what `check` finds wrong) raises WorldUnavailableError (one line);
        without, they are dropped."""
        invalid, refusal = None, None
        replies = self.session.get(
            key, payload=payload or None, timeout=timeout_s,
            target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
        )  # fmt: skip
        for reply in replies:
            sample = reply.ok if reply.ok is not None else reply.err
            data = sample.payload.to_bytes()
            if reply.ok is None and data == _ZENOH_TIMEOUT:
                continue  # the query timed out: no reply
            if not self._from_the_world(key, payload, data, sample.attachment):
                log.warning("%s: dropped a reply not signed by this run's world", key)
                continue
            try:
                message = decode_message(data, kinds, self.services, self._reply_bytes())
            except ProtocolError as error:
                invalid = str(error)
            else:
                if isinstance(message, ErrorReply) and self._step_key is None:
                    refusal = message  # anyone's, unsigned: taken if no valid reply comes
                    continue
                is_error = isinstance(message, ErrorReply)
                invalid = None if check is None or is_error else check(message)
                if invalid is None:
                    return message
            log.warning("%s: dropped a reply: %s", key, invalid)
        if refusal is not None:
            return refusal
        if invalid is not None and check is not None:
            raise WorldUnavailableError(f"{key}: the world's reply is invalid: {invalid}")
        return None

    def _reply_bytes(self) -> int | None:
        """The most a step reply of this world can take (None before `fetch`): every
        robot's scan and claimed map."""
        if self.info is None:
            return None
        robots, rays = len(self.info.starts), self.info.n_rays or 0
        cells = int(np.prod(self.info.shape))
        return map_message_bytes(cells, robots, robots * (3 * rays + 64))

    def _from_the_world(
        self, key: str, query: bytes, reply: bytes, attachment: zenoh.ZBytes | None
    ) -> bool:
        """Whether `reply` (with its `attachment`) carries this run's world's MAC (always
        True without a token)."""
        if self._step_key is None:
            return True
        if attachment is None:
            return False
        return world_reply_signed(self._step_key, key, query, reply, attachment.to_bytes())

    def _step_check(self, request: StepRequest) -> Callable[[Message], str | None]:
        """What is wrong with a reply to step query `request` (None: nothing)."""
        moves = _Moves(self.robot, request, self._poses, self.info)
        return lambda reply: (
            _step_problem(reply, request.seq, self.info, self.world, self._sensor)
            or moves.problem(reply)
        )


def _step_problem(
    reply: Message,
    seq: int,
    info: WorldInfo | None,
    world: World | None,
    sensor: SensorConfig | None,
) -> str | None:
    """Why `reply` is not a valid answer to step `seq` of the world that `info` and `world`
    describe (None before they are known: only the message's own rules hold), or None."""
    if not isinstance(reply, StepReply):
        return f"expected a step_reply, got {reply.TYPE!r}"
    if reply.seq != seq:
        return f"step_reply of step {reply.seq}, not of step {seq}"
    if info is None or world is None:
        return None
    robots, shape = len(info.starts), np.array(info.shape)
    if len(reply.claim_state) != robots:
        return f"step_reply for {len(reply.claim_state)} robots, the run has {robots}"
    scans = 0 if reply.finished else robots
    if len(reply.poses) != scans:
        return f"step_reply with {len(reply.poses)} scans, expected {scans}"
    if scans and info.n_rays is not None and reply.n_cells.shape[1] != info.n_rays:
        return f"step_reply scans of {reply.n_cells.shape[1]} rays, the sensor has {info.n_rays}"
    if ((reply.poses < 0) | (reply.poses >= shape)).any():
        return f"step_reply with a pose outside the {info.shape} map"
    made = reply.claim_state == CLAIM_MADE
    goals, scores = reply.claim_goals[made], reply.claim_scores[made]
    if ((goals < 0) | (goals >= shape)).any():
        return f"step_reply with a claimed goal outside the {info.shape} map"
    if len(reply.claim_visible) and reply.claim_visible.shape[1:] != info.shape:
        return f"step_reply with claimed cells of another shape than the {info.shape} map"
    if np.isnan(scores).any() or (scores == math.inf).any():
        return "step_reply with a claim scored NaN or +inf"
    for robot, pose in enumerate(reply.poses):
        row, col = int(pose[0]), int(pose[1])
        if world.occupancy[row, col]:
            return f"step_reply puts robot {robot_id(robot)} in a wall at {(row, col)}"
        if sensor is not None:
            truth = cast_scan(world.occupancy, (row, col), sensor)
            same_cells = np.array_equal(truth.n_cells, reply.n_cells[robot])
            if not (same_cells and np.array_equal(truth.hit, reply.hit[robot])):
                return f"step_reply scan of robot {robot_id(robot)} contradicts the ground truth"
    return None


class _Moves:
    """The moves a step reply may show: the robot asking is where its request took it (the
    last cell asked) or where it stood (a refused or late motion); a teammate moved at most
    `cells_per_step` cells (one 8-connected move each); at seq 0 everyone is at its start;
    and the team is finished only when this robot said it was done."""

    def __init__(
        self, robot: int, request: StepRequest, poses: np.ndarray | None, info: WorldInfo | None
    ) -> None:
        self.robot, self.request, self.poses, self.info = robot, request, poses, info

    def problem(self, reply: Message) -> str | None:
        """Why the moves `reply` shows cannot have happened, or None."""
        if not isinstance(reply, StepReply) or self.info is None:
            return None
        name = robot_id(self.robot)
        if reply.finished:
            done = self.request.done and self.request.seq > 0
            return None if done else f"step_reply says the team finished, {name} was not done"
        poses = reply.poses
        if self.request.seq == 0 or self.poses is None:
            starts = np.array(self.info.starts, dtype=np.int64).reshape(-1, 2)
            same = starts.shape == poses.shape and np.array_equal(starts, poses)
            return None if same else "step_reply of the initial scans not at the robots' starts"
        own = {tuple(map(int, self.poses[self.robot]))}
        if len(self.request.cells):
            own.add(tuple(map(int, self.request.cells[-1])))
        if tuple(map(int, poses[self.robot])) not in own:
            return f"step_reply moves {name} to {tuple(map(int, poses[self.robot]))}, not asked"
        limit = self.info.cells_per_step
        if limit is not None and len(self.poses) == len(poses):
            jumps = np.abs(poses.astype(np.int64) - self.poses).max(axis=1, initial=0)
            if (jumps > limit).any():
                robot = int(np.argmax(jumps))
                return f"step_reply moves robot {robot_id(robot)} {int(jumps[robot])} cells at once"
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
