"""deploy/: the router process joins sessions that reach each other only through it, and the
deploy files (Zenoh configs, compose and systemd commands) are valid."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from service_processes import (
    REPO_ROOT,
    ROUTER_START_DEADLINE_S,
    STOP_DEADLINE_S,
    free_loopback_port,
    kill_router,
    spawn_router,
    until,
    wait_router_ready,
)

import services.predictor
from deploy import router as deploy_router
from services.config import ServicesConfig
from services.keys import (
    MEMBERS,
    alive_predictor_key,
    alive_predictor_pattern,
    predict_key,
    robot_key,
)
from services.zenoh_config import ZenohConfigError, open_session, zenoh_config

DEPLOY_DIR = REPO_ROOT / "deploy"
HUB = ServicesConfig().hub_endpoint
EXCHANGE_DEADLINE_S = 10.0  # declarations propagate asynchronously; milliseconds when idle


@pytest.fixture(scope="module")
def router(tmp_path_factory):
    """A `python -m deploy.router` process on a free loopback port."""
    started = spawn_router(tmp_path_factory.mktemp("router"), _free_endpoint())
    try:
        wait_router_ready(started)
        yield started
    finally:
        kill_router(started)


def _free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_loopback_port()}"


def _client(endpoint: str, config_file: Path | None = None):
    """A client-mode session whose only link is to `endpoint`."""
    return open_session(zenoh_config("client", [endpoint], config_file=config_file))


def _exchange(server, caller, worker: str) -> None:
    """A put and a query from `caller` reach `server`, and `caller` sees its liveliness token."""
    topic = robot_key("deploy", "r0", "observed_map")
    received: list[bytes] = []
    got_one = threading.Event()

    def on_put(sample) -> None:
        received.append(sample.payload.to_bytes())
        got_one.set()

    def on_query(query) -> None:
        query.reply(query.key_expr, b"answer to " + query.payload.to_bytes())

    subscriber = server.declare_subscriber(topic, on_put)
    queryable = server.declare_queryable(predict_key("g", worker), on_query)
    token = server.liveliness().declare_token(alive_predictor_key("g", worker))
    try:

        def publish() -> bool:  # again until the subscription has reached the caller
            caller.put(topic, b"a map")
            return got_one.wait(0.05)

        until(publish, "the put to arrive", EXCHANGE_DEADLINE_S)
        assert received[0] == b"a map"

        def ask() -> list[bytes]:
            replies = caller.get(predict_key("g", worker), payload=b"q1", timeout=1.0)
            return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]

        assert until(ask, "the query reply", EXCHANGE_DEADLINE_S) == [b"answer to q1"]

        def alive() -> list[str]:
            replies = caller.liveliness().get(alive_predictor_pattern("g"), timeout=1.0)
            return [str(r.ok.key_expr) for r in replies if r.ok is not None]

        assert alive_predictor_key("g", worker) in until(alive, "the token", EXCHANGE_DEADLINE_S)
    finally:
        token.undeclare()
        queryable.undeclare()
        subscriber.undeclare()


def _router_zids(session) -> list[str]:
    return [str(zid) for zid in session.info.routers_zid()]


def test_two_clients_exchange_only_through_the_router(router):
    first = _client(router.endpoint)
    try:
        second = _client(router.endpoint)
        try:
            _exchange(first, second, "w-clients")
            assert _router_zids(first) == _router_zids(second) == [router.zid]
            assert list(first.info.peers_zid()) == list(second.info.peers_zid()) == []
        finally:
            second.close()
    finally:
        first.close()


def test_a_peer_on_another_port_and_a_client_reach_each_other(router):
    peer = open_session(zenoh_config("peer", [router.endpoint], [_free_endpoint()]))
    try:
        client = _client(router.endpoint)
        try:
            _exchange(peer, client, "w-peer")
            _exchange(client, peer, "w-client")
            assert _router_zids(peer) == [router.zid]
        finally:
            client.close()
    finally:
        peer.close()


def test_sigint_stops_the_router_cleanly(tmp_path):
    started = spawn_router(tmp_path, _free_endpoint())
    try:
        wait_router_ready(started)
        client = _client(started.endpoint)
        client_zid = str(client.info.zid())
        until(lambda: f"client {client_zid} joined" in started.log(), "the join line", 10.0)
        client.close()
        started.process.send_signal(signal.SIGINT)
        assert started.process.wait(STOP_DEADLINE_S) == 0, started.log()
        assert "router stopped" in started.log()
    finally:
        kill_router(started)


@pytest.mark.parametrize("endpoint", ["tcp127.0.0.1:7447", "in use"])
def test_an_unusable_listen_endpoint_is_one_line_and_exit_2(endpoint, router):
    endpoint = router.endpoint if endpoint == "in use" else endpoint
    command = [sys.executable, "-m", "deploy.router", "--listen", endpoint]
    try:
        done = subprocess.run(
            command, cwd=REPO_ROOT, capture_output=True, timeout=ROUTER_START_DEADLINE_S
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"the router did not refuse {endpoint}")
    lines = done.stderr.decode(errors="replace").strip().splitlines()
    assert done.returncode == 2, lines
    assert len(lines) == 1 and endpoint in lines[0] and "ERROR" in lines[0]


def _flags(*argv: str):
    return deploy_router.router_config(deploy_router.build_parser().parse_args(list(argv)))


def _get(config, key: str):
    return json.loads(config.get_json(key))


def test_the_default_router_serves_the_loopback_hub_and_dials_nobody():
    config = _flags()
    assert _get(config, "mode") == "router"
    assert _get(config, "listen/endpoints") == [HUB]
    assert _get(config, "connect/endpoints") == []
    assert _get(config, "scouting/multicast/enabled") is False
    everywhere = _flags("--listen", "tcp/0.0.0.0:7447")
    assert _get(everywhere, "connect/endpoints") == []  # never dials the hub, i.e. itself
    linked = _flags("--connect", "tcp/10.0.0.2:7447")
    assert _get(linked, "connect/endpoints") == ["tcp/10.0.0.2:7447"]


def test_a_config_file_keeps_its_endpoints_and_the_mode_is_router(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tcp/10.1.1.1:7447"] } }')
    config = _flags("--config", str(path))
    assert _get(config, "mode") == "router"
    assert _get(config, "connect/endpoints") == ["tcp/10.1.1.1:7447"]
    with pytest.raises(ZenohConfigError, match="bad --listen endpoint"):
        _flags("--listen", "nowhere")


@pytest.mark.parametrize(
    "name, mode, endpoints, mtls",
    [
        ("zenohd.json5", "router", ["tcp/0.0.0.0:7447"], None),
        ("zenohd-tls.json5", "router", ["tls/0.0.0.0:7447"], True),
        ("client-tls.json5", "client", ["tls/router.example.org:7447"], True),
    ],
)
def test_the_zenoh_config_files_parse(name, mode, endpoints, mtls):
    config = zenoh_config(config_file=DEPLOY_DIR / name)
    assert _get(config, "mode") == mode
    key = "connect/endpoints" if mode == "client" else "listen/endpoints"
    assert _get(config, key) == endpoints
    assert _get(config, "scouting/multicast/enabled") is False
    assert _get(config, "transport/link/tls/enable_mtls") is mtls


def test_zenohd_json5_routes_between_clients():
    endpoint = _free_endpoint()
    hub = open_session(zenoh_config(listen=[endpoint], config_file=DEPLOY_DIR / "zenohd.json5"))
    try:
        first, second = _client(endpoint), _client(endpoint)
        try:
            _exchange(first, second, "w-zenohd")
        finally:
            first.close()
            second.close()
    finally:
        hub.close()


def _make_certificates(directory: Path) -> None:
    """A CA and router/worker certificates for localhost (EC P-256)."""
    new_key = ["req", "-nodes", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1"]
    _openssl(
        directory, *new_key, "-x509", "-subj", "/CN=ca", "-keyout", "ca-key.pem", "-out", "ca.pem"
    )
    (directory / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    sign = ["x509", "-req", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial"]
    for name in ("router", "worker"):
        key, request = f"{name}-key.pem", f"{name}.csr"
        _openssl(directory, *new_key, "-subj", f"/CN={name}", "-keyout", key, "-out", request)
        _openssl(directory, *sign, "-extfile", "san.ext", "-in", request, "-out", f"{name}.pem")


def _openssl(directory: Path, *args: str) -> None:
    subprocess.run(["openssl", *args], cwd=directory, check=True, capture_output=True)


def _with_files(config, directory: Path, files: dict[str, str | None]):
    for key, name in files.items():
        path = None if name is None else str(directory / name)
        config.insert_json5(f"transport/link/tls/{key}", json.dumps(path))
    return config


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_the_tls_configs_join_over_mutual_tls_only(tmp_path):
    _make_certificates(tmp_path)
    port = free_loopback_port()
    router_files = {
        "root_ca_certificate": "ca.pem",
        "listen_certificate": "router.pem",
        "listen_private_key": "router-key.pem",
    }
    config = zenoh_config(
        listen=[f"tls/127.0.0.1:{port}"], config_file=DEPLOY_DIR / "zenohd-tls.json5"
    )
    hub = open_session(_with_files(config, tmp_path, router_files))

    def client(certificate: str | None, key: str | None):
        config = zenoh_config(
            connect=[f"tls/localhost:{port}"], config_file=DEPLOY_DIR / "client-tls.json5"
        )
        files = {"root_ca_certificate": "ca.pem", "connect_certificate": certificate}
        return open_session(_with_files(config, tmp_path, {**files, "connect_private_key": key}))

    try:
        first, second = (
            client("worker.pem", "worker-key.pem"),
            client("worker.pem", "worker-key.pem"),
        )
        try:
            _exchange(first, second, "w-tls")
        finally:
            first.close()
            second.close()
        with pytest.raises(ZenohConfigError, match="Unable to connect"):
            client(None, None)  # no client certificate: mTLS refuses it
        with pytest.raises(ZenohConfigError, match="Unable to connect"):
            _client(f"tcp/127.0.0.1:{port}")  # plain TCP to a TLS port
    finally:
        hub.close()


def test_user_password_authentication_refuses_a_wrong_password(tmp_path):
    (tmp_path / "users.txt").write_text("worker:right\n")
    endpoint = _free_endpoint()
    config = zenoh_config("router", [], [endpoint])
    dictionary = {"dictionary_file": str(tmp_path / "users.txt")}
    config.insert_json5("transport/auth/usrpwd", json.dumps(dictionary))
    hub = open_session(config)

    def client(password: str):
        config = zenoh_config("client", [endpoint])
        config.insert_json5(
            "transport/auth/usrpwd", json.dumps({"user": "worker", "password": password})
        )
        return open_session(config)

    try:
        session = client("right")
        try:
            assert _router_zids(session) == [str(hub.info.zid())]
        finally:
            session.close()
        with pytest.raises(ZenohConfigError, match="Unable to connect"):
            client("wrong")
    finally:
        hub.close()


def _compose_commands() -> list[list[str]]:
    """The `command: [...]` lists of deploy/compose.yaml (JSON-style flow sequences)."""
    text = (DEPLOY_DIR / "compose.yaml").read_text()
    return [json.loads(found) for found in re.findall(r"^\s+command: (\[.*\])$", text, re.M)]


def _systemd_command(unit: str, member: str) -> list[str]:
    text = (DEPLOY_DIR / "systemd" / unit).read_text()
    command = re.search(r"^ExecStart=(.*)$", text, re.M).group(1).replace("%i", member)
    defaults = dict(re.findall(r"^Environment=(\w+)=(.*)$", text, re.M))
    return re.sub(r"\$\{(\w+)\}", lambda found: defaults[found.group(1)], command).split()


def _check_command(argv: list[str]) -> str | None:
    """Parse a `python -m MODULE FLAGS` command with its module's parser; the member if any."""
    assert argv[1] == "-m", argv
    parsers = {
        "deploy.router": deploy_router.build_parser,
        "services.predictor": services.predictor.build_parser,
    }
    args = parsers[argv[2]]().parse_args(argv[3:])
    if argv[2] == "deploy.router":
        assert _get(deploy_router.router_config(args), "listen/endpoints") == ["tcp/0.0.0.0:7447"]
        return None
    assert args.mode == "client" and args.connect and args.config is None
    return args.member


def test_compose_and_systemd_commands_are_valid_flags():
    compose_members = [_check_command(argv) for argv in _compose_commands()]
    assert sorted(m for m in compose_members if m) == sorted(MEMBERS)
    assert compose_members.count(None) == 1  # the router
    assert _check_command(_systemd_command("mapex-router.service", "")) is None
    for member in MEMBERS:
        assert _check_command(_systemd_command("mapex-predictor@.service", member)) == member
