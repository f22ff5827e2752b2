"""The world simulator: owns the ground truth and the robots, answers step queries with scans.

    python -m services.world --run RUN_ID [--world default|generated:SEED|KTH_DIR]
        [--robots 1] [--starts 0 [1|ROW,COL ...]] [--mode ...] [--connect ...] [--listen ...]

Robot i of the run is `r<i>` on the wire and starts at `--starts[i]`: a corner 0-3 of the
valid space (`mapex.worlds.start_poses`) or an explicit cell ROW,COL. The process declares,
for each robot, a queryable on `mapex/@v1/<run>/<robot>/step` that answers a StepRequest with
the ScanReply taken after the motion (or an ErrorReply saying why it refused), and publishes
after each step the robot's PoseMessage on `pose` and the ScanReply on `scan`. WorldInfo and
GroundTruth are published once at start on `mapex/@v1/<run>/world_info` and `.../ground_truth`
and served on the same keys, so a late joiner gets them with a `get`. Then it declares the
liveliness token `mapex/@v1/alive/world/<run>` (a live token means every queryable is there).

Steps carry a per-robot sequence number (StepRequest.seq): a repeat of the last one served gets
the cached reply without moving the robot, so a planner may retry a query whose reply was lost.
With a run token in the environment (`MAPEX_RUN_TOKEN`, which services.up sets for the world
and the planners of each run it starts), a step that does not carry that token is refused: a
stray client that can reach the hub cannot move a robot (docs/design.md#trust).
Queries are answered on serving threads, never on Zenoh's own. SIGINT/SIGTERM undeclare
everything, close the session and exit 0. Bad world, starts or flags: one line, exit 2.
"""

from __future__ import annotations

import argparse
import hmac
import logging
import queue
import sys
import threading
from collections.abc import Callable, Sequence

import zenoh

from mapex.config import ExplorationConfig, argparse_type
from mapex.exit_codes import EXIT_USAGE
from mapex.simulator import MotionError, Simulator
from mapex.worlds import DEFAULT_SPEC, StartSpec, World, WorldError, load_world
from mapex.worlds.starts import parse_start, start_cell
from services.codec import DEFAULT_SERVICES, Payload, ProtocolError
from services.config import ServicesConfig
from services.keys import (
    alive_world_key,
    robot_id,
    robot_key,
    run_id_problem,
    run_key,
)
from services.messages import (
    ErrorReply,
    GroundTruth,
    Message,
    PoseMessage,
    ScanReply,
    StepRequest,
    TeamStepRequest,
    WorldInfo,
)
from services.serving import (
    RUN_TOKEN_ENV,
    Answer,
    QueryServers,
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

log = logging.getLogger("services.world")

StepListener = Callable[[int, int, ScanReply], None]
"""Called with (robot index, seq, reply) after each step that moved or scanned anew."""


class StartError(ValueError):
    """A start list the world cannot serve (no robot, a start it cannot take); one line."""


class WorldServer:
    """Turns step payloads into scans for the robots of one world; knows nothing of Zenoh.

    Robot i starts at `starts[i]` (a corner 0-3 or a cell). `answer_step` never raises on
    bad input; it serialises steps, so serving threads of several robots may call it at once.
    `on_step` (settable) hears of every fresh step, e.g. to publish it. With a `run_token`,
    steps that do not carry it are refused before anything else is looked at.
    """

    def __init__(
        self,
        world: World,
        starts: Sequence[StartSpec],
        config: ExplorationConfig = DEFAULT_EXPLORATION,
        on_step: StepListener | None = None,
        run_token: str | None = None,
    ) -> None:
        if not starts:
            raise StartError("a world needs at least one robot")
        clearance = config.world.start_clearance_cells
        try:
            self.starts = [start_cell(world, start, clearance) for start in starts]
        except WorldError as error:
            raise StartError(str(error)) from None
        self.world = world
        self.simulator = Simulator(world, self.starts, config.sensor, config.motion)
        self.on_step = on_step
        self.run_token = run_token
        self.served = 0  # fresh steps served, all robots together
        self._last_seq: list[int | None] = [None] * len(self.starts)
        self._last_reply: list[ScanReply | None] = [None] * len(self.starts)
        self._lock = threading.Lock()

    @property
    def n_robots(self) -> int:
        return len(self.starts)

    def world_info(self) -> WorldInfo:
        """Name, shape, cell size and the start cells of this server's robots."""
        world = self.world
        return WorldInfo(world.name, world.shape, world.resolution_m, self.starts)

    def ground_truth(self) -> GroundTruth:
        """The walls and valid space of the world."""
        return GroundTruth.from_world(self.world)

    request_type: type[StepRequest | TeamStepRequest] = StepRequest  # what a step query holds
    request_name = "step request"  # in refusals

    def answer_step(self, robot: int, payload: Payload | None) -> Message:
        """The reply to a valid step payload of robot `robot` (`_answer`), else an ErrorReply."""
        try:
            if not 0 <= robot < self.n_robots:
                raise ProtocolError(f"robot {robot} is not one of 0-{self.n_robots - 1}")
            if payload is None:
                raise ProtocolError("the query carries no payload")
            request = self.request_type.decode(payload)
        except ProtocolError as error:
            log.warning("refused a malformed %s: %s", self.request_name, error)
            return ErrorReply(f"malformed {self.request_name}: {error}")
        if not self._authorised(request):
            return self._refuse(robot, f"step seq {request.seq} without this run's token")
        return self._answer(robot, request)

    def _answer(self, robot: int, request: StepRequest) -> ScanReply | ErrorReply:
        with self._lock:
            return self._step(robot, request)

    def _step(self, robot: int, request: StepRequest) -> ScanReply | ErrorReply:
        last = self._last_seq[robot]
        if last is not None and request.seq == last:
            return self._last_reply[robot]  # a retry: same reply, no motion
        expected = 0 if last is None else last + 1
        if request.seq != expected:
            return self._refuse(
                robot, f"step seq {request.seq} is out of order, expected {expected}"
            )
        try:
            reply = ScanReply.from_scan(self.simulator.step(robot, request.cells))
        except MotionError as error:
            return self._refuse(robot, f"refused motion: {error}")
        self._last_seq[robot], self._last_reply[robot] = request.seq, reply
        self.served += 1
        if self.on_step is not None:
            self.on_step(robot, request.seq, reply)
        return reply

    def watch_planners(self, session: zenoh.Session, run: str) -> zenoh.LivelinessSubscriber | None:
        """Follow the planners' liveliness (a team world does; one robot's does not)."""
        return None

    def _authorised(self, request: StepRequest | TeamStepRequest) -> bool:
        if self.run_token is None:
            return True
        return hmac.compare_digest((request.run_token or "").encode(), self.run_token.encode())

    def _refuse(self, robot: int, why: str) -> ErrorReply:
        log.warning("robot %s: %s", robot_id(robot), why)
        return ErrorReply(f"robot {robot_id(robot)}: {why}")


def serve(
    session: zenoh.Session,
    server: WorldServer,
    run: str,
    stop: threading.Event,
    services: ServicesConfig = DEFAULT_SERVICES,
) -> int:
    """Serve `server`'s world for `run` on `session` until `stop` is set; return steps served."""
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
    servers = QueryServers(session, answers)
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
        if watcher is not None:
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
                self.publishers[robot, "scan"].put(reply.encode())
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
    exploration: ExplorationConfig = DEFAULT_EXPLORATION,
    services: ServicesConfig = DEFAULT_SERVICES,
    run_token: str | None = None,
    team: bool = False,
) -> int:
    """Serve `world` for `run` with robots at `starts` (corners or cells) until `stop` is set.

    Returns the steps served. Raises StartError or WorldError (bad starts, no start pose) before
    any network set-up, and ZenohConfigError when the session is refused. With `run_token`
    only steps carrying it move a robot. With `team` the robots are one team moved in
    lockstep (`services.team_world`).
    """
    if team:
        from services.team_world import TeamWorldServer

        server = TeamWorldServer(world, starts, exploration, run_token=run_token, services=services)
    else:
        server = WorldServer(world, starts, exploration, run_token=run_token)
    session = open_session(config)
    try:
        return serve(session, server, run, stop or threading.Event(), services)
    finally:
        session.close()


def build_parser() -> argparse.ArgumentParser:
    """The command-line flags: world, run, robots, starts and Zenoh's."""
    parser = argparse.ArgumentParser(
        prog="python -m services.world", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--world",
        default=DEFAULT_SPEC,
        help="'default', 'generated:<seed>', 'generated-open:<seed>' or a KTH map directory "
        "(default: %(default)s)",
    )
    parser.add_argument("--run", required=True, help="run id, the <run> chunk of the keys")
    parser.add_argument("--robots", type=int, default=1, help="number of robots (default: 1)")
    parser.add_argument(
        "--starts",
        type=argparse_type(parse_start),
        nargs="+",
        default=None,
        metavar="CORNER|ROW,COL",
        help="each robot's start: a corner 0-3 or a cell ROW,COL (default: 0 1 ... per robot)",
    )
    parser.add_argument(
        "--team",
        action="store_true",
        help="the robots are one team sharing a map: steps in lockstep, every planner gets "
        "every robot's scan and claims (team_step_request / team_scan_reply)",
    )
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
        config = zenoh_config_from_args(args)
        world = load_world(args.world)
        token = run_token_from_env()
        if token is None:
            log.warning("no %s set: any client that reaches the hub may step", RUN_TOKEN_ENV)
        served = main(config, world, args.run, starts, stop, run_token=token, team=args.team)
    except (WorldError, StartError, ZenohConfigError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    log.info("stopped after serving %d steps", served)
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
    sys.exit(run_cli())
