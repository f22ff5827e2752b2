"""Every key a world, a planner and a viewer need, through the shipped ACL router.

`python -m deploy.router --config deploy/zenohd-acl.json5` runs as a real process, once
with user/password logins and once with client certificates (mTLS); each session below is
a client of it with one role. The world and the planner publish the way their processes
do (declared publishers: `services.world`'s pose and scan, the planner's
`LatestPublisher`; plain puts: the world's world_info and ground_truth), and the
followers subscribe with their processes' patterns (a viewer's `services.watch` /
`services.bridges.follow`, a supervisor's `RunProgress`, a viewer following everything).
Every message must arrive: under the ACL of issue 53 a client's declared publisher never
learned of the subscribers (the router kept their declarations from it) and its puts
mostly never left its process. tests/deploy/test_acl.py shows what each role must NOT do.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zenoh
from acl_router import (
    AUTHS,
    needs_openssl,
    role_config,
    role_session,
    start_acl_router,
)
from service_processes import REPO_ROOT, kill_router, until

from mapex.team.team import Decision
from mapex.worlds import load_world
from services.config import ServicesConfig
from services.keys import (
    alive_planner_key,
    alive_planner_pattern,
    alive_predictor_key,
    alive_predictor_pattern,
    alive_world_key,
    health_key,
    predict_key,
    robot_key,
    robot_key_pattern,
    run_key,
)
from services.latest import LatestPublisher
from services.messages import StatusMessage, StepReply, StepRequest, decode_message
from services.publishing import PUBLISHED_TOPICS
from services.world import WorldServer, serve
from services.world_client import WorldUnavailableError, ZenohWorld

MESSAGES = 10  # numbered puts per key; every one must arrive
SETTLE_DEADLINE_S = 10.0  # until every follower has heard a first put on every key
ARRIVAL_DEADLINE_S = 5.0  # until the numbered puts are all in (milliseconds when idle)
PUT_GAP_S = 0.01
SILENCE_S = 1.0  # how long a denied put must stay unseen after an allowed one arrived
RUN = "aclrun"
ROBOTS = ("r0", "r1")
# what a planner's LatestPublisher publishes: its topics, and the pose where it simulates
# its world itself (services.evaluate's planners, `services.planner --world`)
PLANNER_TOPICS = (*PUBLISHED_TOPICS, "pose")
# the world's processes and the planner's, by the role their user or certificate holds:
# as separate roles, or all as one `runner` (services.up --connect <router> --members none)
CASTS = {
    "roles": {"world": "world", "planner": "planner", "supervisor": "planner"},
    "runner": {"world": "runner", "planner": "runner", "supervisor": "runner"},
}


class Acl:
    """The router of one auth and the sessions opened on it (closed at the end)."""

    def __init__(self, auth: str, directory: Path, edit=None) -> None:
        self.auth, self.directory = auth, directory
        self.router = start_acl_router(directory, auth, edit)
        self.sessions: list[zenoh.Session] = []

    def session(self, role: str) -> zenoh.Session:
        session = role_session(self.router, self.directory, self.auth, role)
        self.sessions.append(session)
        return session

    def close(self) -> None:
        for session in self.sessions:
            session.close()
        kill_router(self.router)


@pytest.fixture(scope="module", params=AUTHS)
def acl(request, tmp_path_factory):
    needs_openssl(request.param)
    router = Acl(request.param, tmp_path_factory.mktemp(f"acl-{request.param}"))
    try:
        yield router
    finally:
        router.close()


class Inbox:
    """(key, payload) of every sample a subscriber got, and the kind of liveliness ones."""

    def __init__(self, label=bytes) -> None:
        """`label`: what a payload says (the text the test put in it)."""
        self.lock = threading.Lock()
        self.label = label
        self.samples: list[tuple[str, bytes, zenoh.SampleKind]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        label = self.label(sample.payload.to_bytes())
        with self.lock:
            self.samples.append((str(sample.key_expr), label, sample.kind))

    def numbered(self, key: str) -> int:
        """How many distinct numbered puts (b"n<i>") arrived on `key`."""
        with self.lock:
            return len({p for k, p, _ in self.samples if k == key and p.startswith(b"n")})

    def heard(self, key: str) -> bool:
        with self.lock:
            return any(k == key for k, _, _ in self.samples)

    def events(self, key: str) -> list[zenoh.SampleKind]:
        with self.lock:
            return [kind for k, _, kind in self.samples if k == key]


def _deliver(send: dict[str, callable], follows: dict[str, tuple[Inbox, list[str]]]) -> None:
    """Put on every key of `send` until each follower heard each of its keys once (the
    declarations have propagated), then MESSAGES numbered puts per key: each follower must
    receive all of them."""
    sent = Counter()

    def put_all(prefix: bytes) -> None:
        for key, put in send.items():
            put(prefix + str(sent[key]).encode())
            sent[key] += 1
        time.sleep(PUT_GAP_S)

    def settled() -> bool:
        put_all(b"probe")
        return all(inbox.heard(key) for inbox, keys in follows.values() for key in keys)

    deadline = time.monotonic() + SETTLE_DEADLINE_S
    while not settled():
        if time.monotonic() > deadline:
            unheard = {
                name: [key for key in keys if not inbox.heard(key)]
                for name, (inbox, keys) in follows.items()
            }
            pytest.fail(f"within {SETTLE_DEADLINE_S} s nothing arrived of {unheard}")
    sent.clear()
    for _ in range(MESSAGES):
        put_all(b"n")

    def counts() -> dict[str, dict[str, int]]:
        return {
            name: {key: inbox.numbered(key) for key in keys}
            for name, (inbox, keys) in follows.items()
        }

    deadline = time.monotonic() + ARRIVAL_DEADLINE_S
    while time.monotonic() < deadline:
        if all(n == MESSAGES for row in counts().values() for n in row.values()):
            break
        time.sleep(0.05)
    missing = {
        name: {key: n for key, n in row.items() if n != MESSAGES} for name, row in counts().items()
    }
    assert missing == {name: {} for name in follows}, f"of {MESSAGES} puts each: {missing}"


def _follow(
    session: zenoh.Session, patterns: list[str], keys: list[str], label=bytes
) -> tuple[Inbox, list]:
    """One inbox fed by subscribers on `patterns`, expected to receive `keys`."""
    inbox = Inbox(label)
    for pattern in patterns:
        session.declare_subscriber(pattern, inbox)
    return inbox, keys


@pytest.mark.parametrize("cast", CASTS)
def test_every_world_key_reaches_viewer_and_supervisor(acl, cast):
    """pose and scan through declared publishers (as services.world), world_info and
    ground_truth by plain puts; a viewer following one run (services.watch's patterns), a
    viewer following everything and the supervisor's progress (RunProgress: every run's
    pose) receive every one."""
    roles = CASTS[cast]
    run = f"{RUN}w{cast}"
    world = acl.session(roles["world"])
    robot_keys = [robot_key(run, robot, topic) for robot in ROBOTS for topic in ("pose", "scan")]
    run_keys = [run_key(run, "world_info"), run_key(run, "ground_truth")]
    follows = {
        "viewer of the run": _follow(
            acl.session("viewer"),
            [robot_key_pattern("pose", run), robot_key_pattern("scan", run), run_keys[0]],
            [*robot_keys, run_keys[0]],
        ),
        "viewer of everything": _follow(
            acl.session("viewer"), ["mapex/@v1/**"], [*robot_keys, *run_keys]
        ),
        "supervisor": _follow(
            acl.session(roles["supervisor"]),
            [robot_key_pattern("pose")],
            [key for key in robot_keys if key.endswith("/pose")],
        ),
    }
    publishers = {key: world.declare_publisher(key) for key in robot_keys}
    send = {key: publisher.put for key, publisher in publishers.items()}
    send.update({key: (lambda payload, key=key: world.put(key, payload)) for key in run_keys})
    _deliver(send, follows)


def _status_detail(payload: bytes) -> bytes:
    return decode_message(payload, (StatusMessage,)).detail.encode()


@pytest.mark.parametrize("cast", CASTS)
def test_every_planner_key_reaches_viewer_and_supervisor_and_late_joiners(acl, cast):
    """Every topic of a planner's LatestPublisher (declared publishers and queryables): a
    viewer per robot topic (services.bridges.follow), a viewer following everything and an
    evaluate supervisor's progress (RunProgress: every run's metrics) receive every put, and
    a late-joining viewer's get is answered with the latest."""
    roles = CASTS[cast]
    run = f"{RUN}p{cast}"
    planner = acl.session(roles["planner"])
    keys = [robot_key(run, "r0", topic) for topic in PLANNER_TOPICS]
    latest = LatestPublisher(planner, keys)
    follows = {
        "viewer of the run": _follow(
            acl.session("viewer"),
            [robot_key_pattern(t, run) for t in PLANNER_TOPICS],
            keys,
            _status_detail,
        ),
        "viewer of everything": _follow(
            acl.session("viewer"), ["mapex/@v1/**"], keys, _status_detail
        ),
        "supervisor": _follow(
            acl.session(roles["supervisor"]),
            [robot_key_pattern("metrics")],
            [robot_key(run, "r0", "metrics")],
            _status_detail,
        ),
    }
    last: dict[str, bytes] = {}

    def sender(key: str):
        def put(payload: bytes) -> None:
            message = StatusMessage(0, "running", payload.decode())
            latest.put(key, message)
            last[key] = message.encode()

        return put

    try:
        _deliver({key: sender(key) for key in keys}, follows)
        viewer = acl.session("viewer")
        for key in keys:
            replies = viewer.get(key, timeout=2.0)
            answers = [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]
            assert answers == [last[key]], key
    finally:
        latest.close()


def test_tokens_come_and_go_at_every_watcher(acl):
    """The world watches its planners' tokens (a robot whose planner left is lost), the
    planner its workers' (ZenohEnsemble), a viewer everyone's: each sees a token appear and,
    when it is undeclared, go."""
    run = f"{RUN}t"
    world, planner, worker = acl.session("world"), acl.session("planner"), acl.session("worker")
    runner_world, runner_planner = acl.session("runner"), acl.session("runner")
    viewer = acl.session("viewer")
    watches = {  # watcher -> (inbox, the tokens it must see come and go)
        "world": (world, alive_planner_pattern(run), [alive_planner_key(run, "r0")]),
        "runner's world": (
            runner_world,
            alive_planner_pattern(run),
            [alive_planner_key(run, "r1")],
        ),
        "planner": (planner, alive_predictor_pattern(), [alive_predictor_key("g", "aclw")]),
        "viewer": (
            viewer,
            "mapex/@v1/alive/**",
            [alive_world_key(run), alive_planner_key(run, "r0"), alive_predictor_key("g", "aclw")],
        ),
    }
    inboxes = {}
    for name, (session, pattern, _) in watches.items():
        inboxes[name] = Inbox()
        session.liveliness().declare_subscriber(pattern, inboxes[name], history=True)
    owners = {
        alive_planner_key(run, "r0"): planner,
        alive_planner_key(run, "r1"): runner_planner,
        alive_predictor_key("g", "aclw"): worker,
        alive_world_key(run): world,
    }
    tokens = {key: owner.liveliness().declare_token(key) for key, owner in owners.items()}
    put, delete = zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE

    def seen(kind) -> bool:
        return all(
            kind in inboxes[name].events(key)
            for name, (_, _, keys) in watches.items()
            for key in keys
        )

    until(lambda: seen(put), "every watcher to see its tokens", SETTLE_DEADLINE_S)
    # a liveliness query (the planner's ZenohEnsemble asks one at start) finds the worker
    replies = planner.liveliness().get(alive_predictor_pattern("g"), timeout=2.0)
    assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [
        alive_predictor_key("g", "aclw")
    ]
    for token in tokens.values():
        token.undeclare()
    until(lambda: seen(delete), "every watcher to see its tokens go", SETTLE_DEADLINE_S)


def test_every_query_a_run_makes_is_answered(acl):
    """The planner's step, world_info and ground_truth (world), predict and health
    (worker); a runner's planner its runner world's step; a viewer's world_info; the oracle
    worker's ground_truth, of a world process and of a planner simulating its world."""
    run = f"{RUN}q"
    world, worker, runner_world = acl.session("world"), acl.session("worker"), acl.session("runner")
    planner, runner_planner, viewer = (
        acl.session("planner"),
        acl.session("runner"),
        acl.session("viewer"),
    )
    served = {
        robot_key(run, "r0", "step"): world,
        run_key(run, "world_info"): world,
        run_key(run, "ground_truth"): world,
        predict_key("g", "aclw"): worker,
        health_key("g", "aclw"): worker,
        robot_key(run, "r1", "step"): runner_world,
    }
    for key, session in served.items():
        session.declare_queryable(key, lambda query: query.reply(query.key_expr, b"answer"))
    evaluated = run_key(f"{run}e", "ground_truth")  # services.evaluate's planner serves it
    planner.declare_queryable(evaluated, lambda query: query.reply(query.key_expr, b"answer"))
    asks = [(planner, key) for key in list(served)[:5]] + [
        (runner_planner, robot_key(run, "r1", "step")),
        (viewer, run_key(run, "world_info")),
        (worker, run_key(run, "ground_truth")),
        (worker, evaluated),
    ]

    def answered(session: zenoh.Session, key: str) -> bool:
        replies = session.get(key, timeout=1.0)
        return [r.ok.payload.to_bytes() for r in replies if r.ok is not None] == [b"answer"]

    for session, key in asks:
        until(lambda s=session, k=key: answered(s, k), f"an answer on {key}", SETTLE_DEADLINE_S)


def test_a_world_role_client_cannot_end_teleport_or_hold_another_run_s_robot(acl):
    """Another user's run (world and planner as `runner`, with their run token) while a
    client holding only the `world` role answers that run's step queries first with the team
    finished and a teleport, and holds others: the planner takes only its world's signed
    replies, so its robot walks as asked, at the world's pace."""
    run, token = f"{RUN}w", "another-user-s-run-token-0b9c"
    world = load_world("generated:0")
    server = WorldServer(world, [0], run_token=token, run=run)
    stop = threading.Event()
    serving = threading.Thread(target=serve, args=(acl.session("runner"), server, run, stop))
    serving.start()
    rogue, held = acl.session("world"), []
    start = server.starts[0]
    far = StepReply(
        0, False, np.array([[world.shape[0] - 2, world.shape[1] - 2]], np.int32),
        np.ones((1, 2500), np.uint16), np.zeros((1, 2500), bool), np.zeros(1, bool),
        np.zeros(1, np.uint8), np.zeros((1, 2), np.int32), np.zeros(1),
        np.zeros((0, *world.shape), bool), np.zeros(1, bool),
    )  # fmt: skip

    def forge(query) -> None:
        seq = StepRequest.decode(query.payload.to_bytes()).seq
        finished = dataclasses.replace(far, seq=seq, finished=True, poses=far.poses[:0],
                                       n_cells=far.n_cells[:0], hit=far.hit[:0])  # fmt: skip
        for reply in (finished, dataclasses.replace(far, seq=seq)):
            query.reply(query.key_expr, reply.encode())

    queryables = [
        rogue.declare_queryable(robot_key(run, "r0", "step"), forge),
        rogue.declare_queryable(robot_key(run, "r0", "step"), held.append),
    ]
    try:
        source = ZenohWorld(acl.session("runner"), run, 0, run_token=token)
        until(lambda: _fetched(source), "the world's info through the router", SETTLE_DEADLINE_S)
        assert source.initial()[0].pose == start
        pose = np.array(start)
        for t in range(5):
            free = [c for c in pose + NEIGHBOURS if not world.occupancy[tuple(c)]]
            pose = np.array(free[t % len(free)])
            began = time.monotonic()
            step = source.step(t, [Decision(0, pose.reshape(1, 2).astype(np.int32))])
            assert not step.finished and step.scans[0].pose == tuple(map(int, pose)), t
            assert time.monotonic() - began < ServicesConfig().step_timeout_s
        assert held  # the rogue's queryable got the queries
    finally:
        for queryable in queryables:
            queryable.undeclare()
        held.clear()
        stop.set()
        serving.join()


NEIGHBOURS = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc])


def _fetched(source: ZenohWorld) -> bool:
    try:
        source.fetch(timeout_s=1.0)
    except WorldUnavailableError:
        return False
    return True


def test_a_run_prefix_in_the_key_expressions_confines_a_planner_to_its_runs(tmp_path):
    """Roles are per process kind, and the run ids are made when a run starts, so the
    shipped file cannot name them; a site can give a planner user its own run prefix
    (`--run-prefix alice-...`) with `$*` (deploy/README.md section 9): then it posts the
    status of its runs and of no other's."""
    shipped = '"mapex/@v1/*/*/status"'

    def alice_only(text: str) -> str:
        assert text.count(shipped) == 2  # planner-publishes and planner-is-asked
        return text.replace(shipped, '"mapex/@v1/alice-$*/*/status"')

    acl = Acl("password", tmp_path, alice_only)
    try:
        planner, viewer = acl.session("planner"), acl.session("viewer")
        inbox = Inbox()
        viewer.declare_subscriber("mapex/@v1/**", inbox)
        own, other = robot_key("alice-0", "r0", "status"), robot_key("bob-0", "r0", "status")
        publishers = {key: planner.declare_publisher(key) for key in (own, other)}

        def posted() -> bool:
            for publisher in publishers.values():
                publisher.put(b"posted")
            time.sleep(PUT_GAP_S)
            return inbox.heard(own)

        until(posted, "the planner's own status", SETTLE_DEADLINE_S)
        time.sleep(SILENCE_S)  # what the router let through of the other run's has arrived
        assert inbox.heard(own) and not inbox.heard(other)
    finally:
        acl.close()


# ---------------------------------------------------------------- real processes, end to end


def _role_file(config: zenoh.Config, path: Path) -> Path:
    """A client config file with the settings of `config` that a role needs."""
    settings = {
        "mode": "client",
        "connect": {"endpoints": json.loads(config.get_json("connect/endpoints"))},
        "scouting": {"multicast": {"enabled": False}},
        "transport": json.loads(config.get_json("transport")),
    }
    path.write_text(json.dumps(settings))
    return path


STEPS = 15
UP_DEADLINE_S = 300.0  # a cold start of every process on a loaded machine


def test_a_run_behind_the_acl_router_shows_its_progress_and_a_viewer_follows_it(
    tmp_path_factory,
):
    """`services.up` logged in as `runner` (its world, planner and supervisor) and
    `services.watch` as `viewer`, through the ACL router with passwords: the progress bar
    reaches every step and the viewer sees the run finish (issue 53: the bar stayed at 0
    and the viewer timed out)."""
    directory = tmp_path_factory.mktemp("acl-e2e")
    acl = Acl("password", directory)
    try:
        runner, viewer = (
            _role_file(role_config(acl.router, directory, "password", role), directory / name)
            for role, name in (("runner", "runner.json5"), ("viewer", "viewer.json5"))
        )
        run = "aclup"
        watch_log = directory / "watch.log"
        with open(watch_log, "wb") as log:
            watch = subprocess.Popen(
                [sys.executable, "-m", "services.watch", "--run", f"{run}-0", "--config",
                 str(viewer), "--png", str(directory / "watch.png"), "--until-finished",
                 "--every-s", "0.5", "--timeout-s", str(UP_DEADLINE_S)],
                cwd=REPO_ROOT, stdout=log, stderr=log,
            )  # fmt: skip
        try:
            up = subprocess.run(
                [sys.executable, "-m", "services.up", "--config", str(runner), "--mode",
                 "client", "--connect", acl.router.endpoint, "--members", "none",
                 "--method", "nearest", "--world", "generated:0", "--steps", str(STEPS),
                 "--run-prefix", run, "--out", str(directory / "runs"),
                 "--set", "services.workers_wait_s=0.5"],  # nearest asks no worker
                cwd=REPO_ROOT, capture_output=True, text=True, timeout=UP_DEADLINE_S,
            )  # fmt: skip
            assert up.returncode == 0, up.stderr
            assert f"{STEPS}/{STEPS}" in up.stderr  # the progress bar, from the world's poses
            assert watch.wait(60) == 0, watch_log.read_text()
        finally:
            if watch.poll() is None:
                watch.kill()
                watch.wait()
    finally:
        acl.close()
