"""deploy/zenohd-acl.json5: a real router process enforces the MapEx roles on real sessions.

Every client is a client-mode session of this process that joins the router with a user
name and password (or, in the last test, a client certificate) and so gets a role: world,
worker, planner or viewer; `rogue` authenticates but has no role. Allowed exchanges are
shown to work first (the positive controls: declarations propagate asynchronously), then
the denied ones are shown to stay silent for `SILENCE_S`: the router drops a denied message
without telling anyone, so "denied" can only be observed as "never arrives".
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from acl_router import make_role_certificates
from service_processes import (
    REPO_ROOT,
    RouterProcess,
    free_loopback_port,
    kill_router,
    until,
    wait_router_ready,
)

from services.keys import (
    alive_planner_key,
    alive_predictor_key,
    alive_world_key,
    predict_key,
    robot_key,
    run_key,
)
from services.zenoh_config import open_session, zenoh_config

ACL_FILE = REPO_ROOT / "deploy" / "zenohd-acl.json5"
DICTIONARY = "/etc/mapex/zenoh-users.txt"  # as written in ACL_FILE, replaced by a tmp file
USERS = {  # user -> password; the role is the user name, `rogue` matches no subject
    "world": "w0rld",
    "worker": "w0rker",
    "planner": "pl4nner",
    "viewer": "v1ewer",
    "runner": "runn3r",
    "rogue": "r0gue",
}
# A role's second session stands for a hostile process holding that role's credentials
# (it must not be the session that checks: Zenoh delivers a session's own messages locally).
SESSIONS = {
    "world": "world",
    "worker": "worker",
    "planner": "planner",
    "planner2": "planner",
    "viewer": "viewer",
    "viewer2": "viewer",
    "runner": "runner",
    "runner2": "runner",
    "rogue": "rogue",
}
EXCHANGE_DEADLINE_S = 10.0  # positive controls; milliseconds when idle
SILENCE_S = 1.5  # how long a denied message must stay unseen after the control passed

STEP = robot_key("run0", "r0", "step")
STATUS = robot_key("run0", "r0", "status")
POSE = robot_key("run0", "r0", "pose")
WORKER = predict_key("g", "w1")
HEALTH = "mapex/@v1/health/g/w1"  # the health probe of worker w1 (services.keys health_key)


@pytest.fixture(scope="module")
def acl_router(tmp_path_factory):
    """`python -m deploy.router --config <zenohd-acl.json5 with a tmp dictionary> --listen
    tcp/127.0.0.1:<free port>` as a real process."""
    directory = tmp_path_factory.mktemp("acl")
    users = directory / "zenoh-users.txt"
    users.write_text("".join(f"{user}:{password}\n" for user, password in USERS.items()))
    text = ACL_FILE.read_text()
    assert text.count(DICTIONARY) == 1
    config_file = directory / "zenohd-acl.json5"
    config_file.write_text(text.replace(DICTIONARY, str(users)))
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    command = [sys.executable, "-m", "deploy.router", "--config", str(config_file)]
    log_path = directory / "router.log"
    with open(log_path, "wb") as log:
        process = subprocess.Popen(
            [*command, "--listen", endpoint], cwd=REPO_ROOT, stdout=log, stderr=log
        )
    router = RouterProcess(process, log_path, endpoint)
    try:
        wait_router_ready(router)
        yield router
    finally:
        kill_router(router)


@pytest.fixture(scope="module")
def sessions(acl_router):
    """One client session per entry of SESSIONS, each logged in as its role's user."""
    opened: dict[str, zenoh.Session] = {}
    try:
        for name, user in SESSIONS.items():
            opened[name] = _client(acl_router.endpoint, user, USERS[user])
        yield opened
    finally:
        for session in opened.values():
            session.close()


def _client(endpoint: str, user: str, password: str) -> zenoh.Session:
    config = zenoh_config("client", [endpoint])
    credentials = {"user": user, "password": password}
    config.insert_json5("transport/auth/usrpwd", json.dumps(credentials))
    return open_session(config)


def _answering(session: zenoh.Session, key: str, answer: bytes):
    """A queryable on `key` replying `answer`."""
    return session.declare_queryable(key, lambda query: query.reply(query.key_expr, answer))


def _ask(session: zenoh.Session, key: str, timeout_s: float = 1.0) -> list[bytes]:
    return _answers(session.get(key, timeout=timeout_s))


def _answers(replies) -> list[bytes]:
    return [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]


def _asked_until(session: zenoh.Session, key: str, expected: list[bytes]) -> None:
    """Query `key` again until the replies are `expected` (the queryable has propagated)."""
    until(lambda: _ask(session, key) == expected, f"{expected} on {key}", EXCHANGE_DEADLINE_S)


def _late_queries(queries: dict[str, tuple[zenoh.Session, str]]) -> dict[str, list[bytes]]:
    """Wait SILENCE_S (so that every declaration made before has reached the router), send
    every query at once and return the answers each got. A query the router drops ends at
    once with no reply (eclipse-zenoh 1.10), so this waits no longer."""
    time.sleep(SILENCE_S)
    pending = {name: session.get(key, timeout=1.0) for name, (session, key) in queries.items()}
    return {name: _answers(replies) for name, replies in pending.items()}


class _Inbox:
    """The payloads a subscriber (or liveliness subscriber) has received."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.items: list[tuple[str, bytes]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def payloads(self) -> list[bytes]:
        with self.lock:
            return [payload for _, payload in self.items]

    def keys(self) -> list[str]:
        with self.lock:
            return [key for key, _ in self.items]


def test_the_acl_config_loads_with_a_policy_per_role_by_user_and_by_cn():
    config = zenoh.Config.from_file(str(ACL_FILE))
    acl = json.loads(config.get_json("access_control"))
    assert json.loads(config.get_json("mode")) == "router"
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    usrpwd = json.loads(config.get_json("transport/auth/usrpwd"))
    assert usrpwd["dictionary_file"] == DICTIONARY
    subjects = {subject["id"]: subject for subject in acl["subjects"]}
    rules = {rule["id"] for rule in acl["rules"]}
    roles = {}
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= rules, policy["id"]
        matched = [subjects[name] for name in policy["subjects"]]
        roles[policy["id"]] = (
            {user for subject in matched for user in subject["usernames"] or ()},
            {cn for subject in matched for cn in subject["cert_common_names"] or ()},
        )
    assert roles == {
        "world": ({"world"}, {"mapex-world"}),
        "worker": ({"worker", "worker-a", "worker-b"}, {"mapex-worker"}),
        "planner": ({"planner"}, {"mapex-planner"}),
        "runner": ({"runner"}, {"mapex-runner"}),
        "viewer": ({"viewer"}, {"mapex-viewer"}),
    }


def test_only_the_planner_moves_a_robot(sessions):
    queryable = _answering(sessions["world"], STEP, b"stepped")
    try:
        _asked_until(sessions["planner"], STEP, [b"stepped"])
        denied = _late_queries(
            {name: (sessions[name], STEP) for name in ("worker", "viewer", "rogue")}
        )
        assert denied == {"worker": [], "viewer": [], "rogue": []}
    finally:
        queryable.undeclare()


def test_a_runner_is_world_and_planner_but_never_a_worker(sessions):
    """services.up's machine: world and planners log in as one `runner` user."""
    runner, runner2, worker = sessions["runner"], sessions["runner2"], sessions["worker"]
    declared = [
        _answering(runner, STEP, b"stepped"),
        _answering(worker, WORKER, b"prediction"),
        _answering(runner2, predict_key("g", "fake"), b"impostor"),
    ]
    try:
        _asked_until(runner2, STEP, [b"stepped"])  # its planner moves its world's robot
        _asked_until(runner, WORKER, [b"prediction"])  # and asks the workers
        answers = _late_queries({"impostor": (sessions["planner"], predict_key("g", "fake"))})
        assert answers == {"impostor": []}
    finally:
        for entity in declared:
            entity.undeclare()


def test_the_world_publishes_and_serves_its_keys(sessions):
    world, viewer = sessions["world"], sessions["viewer"]
    info = run_key("run0", "world_info")
    inbox = _Inbox()
    subscriber = viewer.declare_subscriber(POSE, inbox)
    queryable = _answering(world, info, b"info")
    try:

        def published() -> bool:
            world.put(POSE, b"pose")
            time.sleep(0.05)
            return b"pose" in inbox.payloads()

        until(published, "the world's pose at the viewer", EXCHANGE_DEADLINE_S)
        _asked_until(sessions["planner"], info, [b"info"])  # a planner starting
        _asked_until(viewer, info, [b"info"])  # a late-joining viewer
    finally:
        queryable.undeclare()
        subscriber.undeclare()


def test_only_a_worker_serves_predictions_and_health(sessions):
    worker, planner = sessions["worker"], sessions["planner"]
    impostors = {  # a planner-, viewer- and no-role process pretending to be workers
        "planner2": predict_key("g", "fake"),
        "viewer2": predict_key("g", "fake2"),
        "rogue": predict_key("g", "rogue"),
    }
    # worker ids that the planner's and world's own patterns (mapex/@v1/*/*/goal, .../step)
    # would match if the guard rules did not keep them out of the worker namespace
    lookalikes = {"planner2": predict_key("g", "goal"), "world": predict_key("g", "step")}
    declared = [
        _answering(worker, WORKER, b"prediction"),
        _answering(worker, HEALTH, b"healthy"),
        *(_answering(sessions[name], key, name.encode()) for name, key in impostors.items()),
        *(_answering(sessions[name], key, name.encode()) for name, key in lookalikes.items()),
    ]
    try:
        _asked_until(planner, WORKER, [b"prediction"])
        _asked_until(planner, HEALTH, [b"healthy"])
        queries = {name: (planner, key) for name, key in {**impostors, **lookalikes}.items()}
        queries["every g worker"] = (planner, "mapex/@v1/predict/g/*")
        queries["viewer asks"] = (sessions["viewer"], WORKER)  # predictions are not a viewer's
        queries["rogue asks"] = (sessions["rogue"], WORKER)
        answers = _late_queries(queries)
        assert answers.pop("every g worker") == [b"prediction"]  # the impostors stay silent
        assert answers == {name: [] for name in answers}
    finally:
        for entity in declared:
            entity.undeclare()


def test_only_the_planner_publishes_its_robot_topics(sessions):
    planner, viewer = sessions["planner"], sessions["viewer"]
    inbox = _Inbox()
    subscriber = viewer.declare_subscriber("mapex/@v1/**", inbox)
    latest = _answering(planner, STATUS, b"latest status")  # what a late joiner gets
    try:

        def published() -> bool:
            planner.put(STATUS, b"planner")
            time.sleep(0.05)
            return b"planner" in inbox.payloads()

        until(published, "the planner's status at the viewer", EXCHANGE_DEADLINE_S)
        _asked_until(viewer, STATUS, [b"latest status"])
        hostile = ("viewer2", "worker", "world", "rogue")
        for name in hostile:
            sessions[name].put(STATUS, name.encode())
        sessions["worker"].put(predict_key("g", "w1"), b"worker-put")  # serving is not putting
        time.sleep(SILENCE_S)
        planner.put(STATUS, b"after")
        until(lambda: b"after" in inbox.payloads(), "the planner's later status", 5.0)
        received = set(inbox.payloads())
        assert received.isdisjoint({name.encode() for name in hostile} | {b"worker-put"})
    finally:
        latest.undeclare()
        subscriber.undeclare()


def test_the_planner_sees_the_liveliness_token_of_each_role(sessions):
    planner = sessions["planner"]
    tokens = {
        "world": alive_world_key("run0"),
        "worker": alive_predictor_key("g", "w1"),
        "planner2": alive_planner_key("run0", "r0"),  # another planner: not the one that looks
    }
    forged = {  # tokens of roles these sessions do not hold
        "rogue": alive_predictor_key("g", "rogue"),
        "viewer2": alive_planner_key("forged", "r0"),
        "world": alive_predictor_key("g", "world"),
    }
    declared = [
        sessions[name].liveliness().declare_token(key)
        for name, key in [*tokens.items(), *forged.items()]
    ]
    watched = _Inbox()
    watcher = planner.liveliness().declare_subscriber("mapex/@v1/alive/**", watched, history=True)
    try:

        def alive() -> set[str]:
            replies = planner.liveliness().get("mapex/@v1/alive/**", timeout=1.0)
            return {str(reply.ok.key_expr) for reply in replies if reply.ok is not None}

        expected = set(tokens.values())
        until(lambda: alive() == expected, "the three tokens", EXCHANGE_DEADLINE_S)
        until(lambda: set(watched.keys()) == expected, "the subscriber", EXCHANGE_DEADLINE_S)
        time.sleep(SILENCE_S)
        # no forged token, even later (a liveliness query on a loaded machine may time out
        # empty: ask until one is answered; a forged token would never let it equal)
        until(lambda: alive() == expected, "the same three tokens later", EXCHANGE_DEADLINE_S)
        assert set(watched.keys()) == expected
    finally:
        watcher.undeclare()
        for token in declared:
            token.undeclare()


def test_a_rogue_user_receives_nothing(sessions):
    planner, viewer, rogue = sessions["planner"], sessions["viewer"], sessions["rogue"]
    viewer_inbox, rogue_inbox, rogue_tokens = _Inbox(), _Inbox(), _Inbox()
    subscribers = [
        viewer.declare_subscriber(STATUS, viewer_inbox),
        rogue.declare_subscriber("mapex/@v1/**", rogue_inbox),
        rogue.liveliness().declare_subscriber("mapex/@v1/**", rogue_tokens, history=True),
    ]
    token = planner.liveliness().declare_token(alive_planner_key("run1", "r0"))
    try:

        def published() -> bool:
            planner.put(STATUS, b"for the viewer only")
            time.sleep(0.05)
            return bool(viewer_inbox.payloads())

        until(published, "the status at the viewer", EXCHANGE_DEADLINE_S)
        time.sleep(SILENCE_S)
        assert _answers(rogue.liveliness().get("mapex/@v1/**", timeout=1.0)) == []
        assert rogue_inbox.items == rogue_tokens.items == []
    finally:
        token.undeclare()
        for subscriber in subscribers:
            subscriber.undeclare()


# ------------------------------------------------------------------ certificate common names


def _tls(config: zenoh.Config, directory: Path, files: dict[str, str]) -> zenoh.Config:
    tls = {key: str(directory / name) for key, name in files.items()}
    config.insert_json5("transport/link/protocols", json.dumps(["tls"]))
    config.insert_json5("transport/link/tls", json.dumps({**tls, "enable_mtls": True}))
    return config


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_certificate_common_names_pick_the_role(tmp_path):
    """The same rules by CN: over mutual TLS without passwords, `mapex-planner` may publish
    the status and `mapex-viewer` may not."""
    make_role_certificates(tmp_path, ("mapex-planner", "mapex-viewer"))
    port = free_loopback_port()
    config = zenoh_config(listen=[f"tls/127.0.0.1:{port}"], config_file=ACL_FILE)
    config.insert_json5("transport/auth/usrpwd/dictionary_file", "null")  # CNs only
    router_files = {
        "root_ca_certificate": "ca.pem",
        "listen_certificate": "router.pem",
        "listen_private_key": "router-key.pem",
    }
    router = open_session(_tls(config, tmp_path, router_files))

    def client(cn: str) -> zenoh.Session:
        files = {
            "root_ca_certificate": "ca.pem",
            "connect_certificate": f"{cn}.pem",
            "connect_private_key": f"{cn}-key.pem",
        }
        return open_session(
            _tls(zenoh_config("client", [f"tls/localhost:{port}"]), tmp_path, files)
        )

    opened: list[zenoh.Session] = []
    try:
        for cn in ("mapex-planner", "mapex-viewer", "mapex-viewer"):
            opened.append(client(cn))
        planner, viewer, other_viewer = opened
        inbox = _Inbox()
        subscriber = viewer.declare_subscriber(STATUS, inbox)

        def published() -> bool:
            planner.put(STATUS, b"planner")
            time.sleep(0.05)
            return b"planner" in inbox.payloads()

        until(published, "the planner's status over mTLS", EXCHANGE_DEADLINE_S)
        other_viewer.put(STATUS, b"viewer")
        time.sleep(SILENCE_S)
        assert b"viewer" not in inbox.payloads()
        subscriber.undeclare()
    finally:
        for session in opened:
            session.close()
        router.close()
