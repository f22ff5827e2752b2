"""The world simulator: owns the ground truth and the robots, and is their clock.

Every run is a team of N >= 1 robots (docs/algorithms.md#teams): the world answers the
step queries of the robots' planners in lockstep, one step for all, and every planner gets
every robot's scan and the claims made at that step. It publishes each robot's pose and
scan, and its world_info and ground truth (also served to late joiners). Keys, messages,
sequence numbers, retries and the signed steps of a run with a token: docs/protocol.md.
A bad world (one above `world.max_cells` too), starts or flags: one line, exit 2;
SIGINT/SIGTERM: a clean stop, exit 0.
"""

from __future__ import annotations

import argparse
import logging
import queue
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence

import numpy as np
import zenoh

from mapex.config import ConfigError, ExplorationConfig, argparse_type
from mapex.exit_codes import EXIT_USAGE
from mapex.simulator import MotionError, Simulator
from mapex.worlds import (
    DEFAULT_SPEC,
    StartSpec,
    World,
    WorldError,
    load_world,
    world_spec_help,
)
from mapex.worlds.starts import parse_start, start_cell
from services.codec import DEFAULT_SERVICES, Payload, ProtocolError
from services.config import RunConfig, ServicesConfig, add_run_config_argument
from services.keys import (
    ROBOT_ID_PREFIX,
    AliveKey,
    alive_planner_pattern,
    alive_world_key,
    parse_key,
    robot_id,
    robot_key,
    run_id_problem,
    run_key,
)
from services.messages import (
    CLAIM_MADE,
    CLAIM_WITHDRAWN,
    ErrorReply,
    GroundTruth,
    Message,
    PoseMessage,
    ScanReply,
    StepReply,
    StepRequest,
    WorldInfo,
    map_message_bytes,
    step_key,
    world_reply_mac,
)
from services.serving import (
    RUN_TOKEN_ENV,
    Answer,
    QueryServers,
    Signer,
    configure_logging,
    run_token_from_env,
    stop_on_signals,
    wait_for,
)
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)

DEFAULT_EXPLORATION = ExplorationConfig()
DEFAULT_RUN_CONFIG = RunConfig()
KEPT_REPLIES = 4  # steps whose reply is kept for late requests and retries

log = logging.getLogger("services.world")

StepListener = Callable[[int, int, ScanReply], None]
"""Called with (robot index, seq, reply) after each step that moved or scanned anew."""


class StartError(ValueError):
    """A start list the world cannot serve (no robot, a start it cannot take); one line."""


class WorldServer:
    """The robots of one world, stepped in lockstep; knows nothing of Zenoh.

    Robot i starts at `starts[i]` (a corner 0-3 or a cell). A `step_request` of seq s waits
    until every robot's request of seq s is in (or `services.team_step_wait_s` has passed
    since the first arrived: a late robot stands still for that step); then every robot
    moves and every request gets the same `StepReply`. A request for a recent seq (a retry,
    or a robot that was late) gets that step's reply again; its motion is not applied. A
    robot whose planner is gone is not waited for and its claim is withdrawn. The reply says
    `finished` (nobody moves) when every robot left has nothing left to explore.
    `answer_step` never raises on bad input and may be called from several threads at once;
    `on_step` (settable) hears of every robot's fresh scan. With a `run_token` (and the `run`
    it belongs to), a request that does not carry its MAC under `step_key(run_token, run)`
    for this robot is refused before anything else is looked at; a claim that does not fit
    the world (its goal outside the map, its cells another shape) is refused too.
    """

    def __init__(
        self,
        world: World,
        starts: Sequence[StartSpec],
        config: ExplorationConfig = DEFAULT_EXPLORATION,
        on_step: StepListener | None = None,
        run_token: str | None = None,
        services: ServicesConfig = DEFAULT_SERVICES,
        run: str | None = None,
    ) -> None:
        if run_token is not None and run is None:
            raise ValueError("a world with a run token needs the run id its steps are signed for")
        if not starts:
            raise StartError("a world needs at least one robot")
        clearance = config.world.start_clearance_cells
        try:
            self.starts = [start_cell(world, start, clearance) for start in starts]
        except WorldError as error:
            raise StartError(str(error)) from None
        self.world = world
        self.config = config
        self.simulator = Simulator(world, self.starts, config.sensor, config.motion)
        self.on_step = on_step
        self.run = run
        self._step_key = None if run_token is None else step_key(run_token, run or "")
        self.services = services
        # a request holds its motion and at most one claimed map of the world
        cells_per_step = config.motion.cells_per_step
        self._request_bytes = map_message_bytes(world.occupancy.size, 1, 8 * cells_per_step)
        self.served = 0  # robot scans taken, all robots together
        self.seq = 0  # the step being collected (0: the initial scans)
        self.lost: set[int] = set()
        self.finished = False  # a step reply said so: every robot left was done
        self._requests: dict[int, StepRequest] = {}
        self._first_arrival: float | None = None
        self._replies: OrderedDict[int, StepReply] = OrderedDict()
        self._clock = threading.Condition()
        self._announced: set[int] = set()  # lost robots whose claim was withdrawn

    @property
    def n_robots(self) -> int:
        return len(self.starts)

    def world_info(self) -> WorldInfo:
        """Name, shape, cell size, the robots' start cells, and the sensor and motion
        settings every planner of the run must share."""
        world, config = self.world, self.config
        return WorldInfo(
            world.name, world.shape, world.resolution_m, self.starts,
            config.sensor.n_rays, config.sensor.range_cells, config.motion.cells_per_step,
        )  # fmt: skip

    def ground_truth(self) -> GroundTruth:
        """The walls and valid space of the world."""
        return GroundTruth.from_world(self.world)

    def answer_step(self, robot: int, payload: Payload | None) -> Message:
        """The reply to a valid step payload of robot `robot`, else an ErrorReply."""
        try:
            if not 0 <= robot < self.n_robots:
                raise ProtocolError(f"robot {robot} is not one of 0-{self.n_robots - 1}")
            if payload is None:
                raise ProtocolError("the query carries no payload")
            request = StepRequest.decode(payload, self.services, self._request_bytes)
        except ProtocolError as error:
            log.warning("refused a malformed step request: %s", error)
            return ErrorReply(f"malformed step request: {error}")
        if not self._authorised(robot, request):
            why = f"step seq {request.seq} without this run's token's signature"
            return self._refuse(robot, why)
        if (problem := self._claim_problem(request)) is not None:
            return self._refuse(robot, f"step seq {request.seq}: {problem}")
        with self._clock:
            return self._wait_for_step(robot, request)

    def reply_signer(self) -> Signer | None:
        """With a run token: what signs every reply this world sends (`world_reply_mac`
        under the run's step key), so that its planners take no other answer; else None."""
        key = self._step_key
        if key is None:
            return None
        return lambda key_expr, query, reply: world_reply_mac(key, key_expr, query, reply)

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
                # a planner leaves after the budget's last step, or when G's IoU or coverage
                # reached the level (the world does not see that): only an earlier exit is a loss
                budget = self.config.steps
                stops = (self.config.until_iou, self.config.metrics.until_coverage)
                ended = self.seq > budget or self.finished or stops != (None, None)
                if ended:  # a planner that finished: not a lost robot
                    log.info("robot %s's planner finished (at step %d)", robot_id(robot), self.seq)
                else:
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

    def _wait_for_step(self, robot: int, request: StepRequest) -> StepReply | ErrorReply:
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
        self.finished = self.finished or finished
        scans = []
        if not finished:
            scans = [self._move(robot, seq, requests.get(robot)) for robot in range(self.n_robots)]
        self._replies[seq] = self._team_reply(seq, finished, scans, requests, late)
        while len(self._replies) > KEPT_REPLIES:
            self._replies.popitem(last=False)
        self.seq, self._requests, self._first_arrival = seq + 1, {}, None
        self._clock.notify_all()

    def _move(self, robot: int, seq: int, request: StepRequest | None) -> ScanReply:
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
        requests: dict[int, StepRequest],
        late: list[int],
    ) -> StepReply:
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
        return StepReply(
            seq, finished,
            np.array([s.pose for s in scans], dtype=np.int32).reshape(-1, 2),
            np.array([s.n_cells for s in scans], dtype=np.uint16).reshape(len(scans), rays),
            np.array([s.hit for s in scans], dtype=bool).reshape(len(scans), rays),
            stood, state, goals, scores,
            visible.reshape(len(made), *shape), lost,
        )  # fmt: skip

    def _authorised(self, robot: int, request: StepRequest) -> bool:
        if self._step_key is None:
            return True
        return request.signed_by(self._step_key, self.run or "", robot)

    def _claim_problem(self, request: StepRequest) -> str | None:
        """Why the claim of `request` does not fit this world, or None (no claim, or it fits)."""
        if request.claim_goal is None:
            return None
        shape = self.world.shape
        if not (request.claim_goal[0] < shape[0] and request.claim_goal[1] < shape[1]):
            return f"claim_goal {request.claim_goal} lies outside the {shape} map"
        if request.claim_visible.shape != shape:
            return f"claim_visible has shape {request.claim_visible.shape}, the map {shape}"
        return None

    def _refuse(self, robot: int, why: str) -> ErrorReply:
        log.warning("robot %s: %s", robot_id(robot), why)
        return ErrorReply(f"robot {robot_id(robot)}: {why}")


def _robot_index(robot: str | None) -> int | None:
    """The index of robot id `r<k>`, or None."""
    if robot is None or not robot.startswith(ROBOT_ID_PREFIX) or not robot[1:].isdigit():
        return None
    return int(robot[1:])


def serve(
    session: zenoh.Session,
    server: WorldServer,
    run: str,
    stop: threading.Event,
    services: ServicesConfig = DEFAULT_SERVICES,
) -> int:
    """Serve `server`'s world for `run` on `session` until `stop` is set; return steps served."""
    if server.run is not None and server.run != run:
        raise ValueError(f"the world's steps are signed for run {server.run!r}, not {run!r}")
    publishers = _declare_step_publishers(session, server, run)
    step_publisher = _StepPublisher(publishers)
    server.on_step = step_publisher
    info, truth = server.world_info(), server.ground_truth()
    answers: dict[str, Answer] = {
        run_key(run, "world_info"): lambda *_: info,
        run_key(run, "ground_truth"): lambda *_: truth,
    }
    for robot in range(server.n_robots):
        answers[robot_key(run, robot_id(robot), "step")] = _step_answerer(server, robot)
    servers = QueryServers(session, answers, server.reply_signer())
    session.put(run_key(run, "world_info"), info.encode())
    session.put(run_key(run, "ground_truth"), truth.encode())
    token = session.liveliness().declare_token(alive_world_key(run))
    watcher = server.watch_planners(session, run)
    log.info(
        "serving world %s %s for run %s: robots at %s", info.name, info.shape, run, server.starts
    )
    try:
        wait_for(stop)
    finally:
        token.undeclare()
        watcher.undeclare()
        servers.close(services.world_drain_s)
        step_publisher.close()
        for publisher in publishers.values():
            publisher.undeclare()
    return server.served


def _declare_step_publishers(
    session: zenoh.Session, server: WorldServer, run: str
) -> dict[tuple[int, str], zenoh.Publisher]:
    """A `pose` and a `scan` publisher per robot, keyed by (robot index, topic)."""
    return {
        (robot, topic): session.declare_publisher(robot_key(run, robot_id(robot), topic))
        for robot in range(server.n_robots)
        for topic in ("pose", "scan")
    }


class _StepPublisher:
    """Publishes each fresh step's pose (t = seq: the initial scan is t = 0) and scan from a
    thread of its own, so encoding them does not delay the step's reply."""

    def __init__(self, publishers: dict[tuple[int, str], zenoh.Publisher]) -> None:
        self.publishers = publishers
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._run, name="publish steps", daemon=True)
        self.thread.start()

    def __call__(self, robot: int, seq: int, reply: ScanReply) -> None:
        self.queue.put((robot, seq, reply))

    def close(self) -> None:
        """Publish what is queued, then stop."""
        self.queue.put(None)
        self.thread.join()

    def _run(self) -> None:
        while (item := self.queue.get()) is not None:
            robot, seq, reply = item
            try:
                self.publishers[robot, "pose"].put(PoseMessage(seq, reply.pose).encode())
                scan = ScanReply(reply.pose, reply.n_cells, reply.hit, t=seq)  # with its step
                self.publishers[robot, "scan"].put(scan.encode())
            except zenoh.ZError as error:
                log.warning("could not publish step %d of robot %d: %s", seq, robot, error)


def _step_answerer(server: WorldServer, robot: int) -> Answer:
    return lambda payload, _waited_s: server.answer_step(robot, payload)


def main(
    config: zenoh.Config,
    world: World,
    run: str,
    starts: Sequence[StartSpec],
    stop: threading.Event | None = None,
    run_config: RunConfig = DEFAULT_RUN_CONFIG,
    run_token: str | None = None,
) -> int:
    """Serve `world` for `run` with robots at `starts` (corners or cells) until `stop` is set.

    Returns the robot scans served. Raises StartError or WorldError (bad starts, no start
    pose) before any network set-up, and ZenohConfigError when the session is refused. With
    `run_token` only steps signed with its key for this run move a robot.
    """
    server = WorldServer(
        world, starts, run_config.exploration, run_token=run_token,
        services=run_config.services, run=run,
    )  # fmt: skip
    session = open_session(config)
    try:
        return serve(session, server, run, stop or threading.Event(), run_config.services)
    finally:
        session.close()


def build_parser() -> argparse.ArgumentParser:
    """The command-line flags: world, run, robots, starts, settings and Zenoh's."""
    parser = argparse.ArgumentParser(
        prog="python -m services.world", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--world",
        default=DEFAULT_SPEC,
        help=f"the world: {world_spec_help()} (default: %(default)s)",
    )
    parser.add_argument("--run", required=True, help="run id, the <run> chunk of the keys")
    parser.add_argument(
        "--robots", type=int, default=1, help="robots of the run, one team (default: 1)"
    )
    parser.add_argument(
        "--starts",
        type=argparse_type(parse_start),
        nargs="+",
        default=None,
        metavar="CORNER|ROW,COL",
        help="each robot's start: a corner 0-3 or a cell ROW,COL (default: 0 1 ... per robot)",
    )
    add_run_config_argument(parser)
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    """Parse flags, serve until SIGINT/SIGTERM; 0 on a clean stop, 2 on a one-line error."""
    parser = build_parser()
    args = parser.parse_args(argv)
    starts = list(range(args.robots)) if args.starts is None else args.starts
    _check_flags(parser, args, starts)
    configure_logging(f"world[{args.run}]")
    stop = stop_on_signals()
    try:
        run_config = RunConfig().with_overrides(args.overrides)
        run_config.exploration.team.check_robots(args.robots)
        config = zenoh_config_from_args(args, run_config.services)
        world = load_world(args.world, run_config.exploration.world.max_cells)
        token = run_token_from_env()
        if token is None:
            log.warning("no %s set: any client that reaches the hub may step", RUN_TOKEN_ENV)
        log.info("%s", run_config.describe())
        served = main(config, world, args.run, starts, stop, run_config, token)
    except (WorldError, StartError, ConfigError, ZenohConfigError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    log.info("stopped after serving %d scans", served)
    return 0


def _check_flags(
    parser: argparse.ArgumentParser, args: argparse.Namespace, starts: list[StartSpec]
) -> None:
    """argparse-style one-line errors (exit 2) for flag values argparse cannot check itself."""
    if (problem := run_id_problem(args.run)) is not None:
        parser.error(problem)
    if args.robots < 1:
        parser.error(f"--robots must be at least 1, got {args.robots}")
    if len(starts) != args.robots:
        parser.error(f"--starts names {len(starts)} starts for {args.robots} robots")


if __name__ == "__main__":
    from services.serving import exit_on_signals

    exit_on_signals(until_serving=True)  # a signal before serving ends the process at once
    sys.exit(run_cli())
