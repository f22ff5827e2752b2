"""The live Foxglove server (services.bridges.foxglove_live) seen by a Foxglove WebSocket
client (tests/helpers/foxglove_client.py): its subprotocol, latched topics for a late
subscriber, refused subscriptions answered with the channel made again (the SDK's
advertise/subscribe race), the relay's cap on clients and its handshake deadline, a real
`services.up --foxglove` run whose every channel delivers in five sessions in a row (the
server a child process of up), and a busy port refused in one line, by up and by the
`services.foxglove` command.

Ports are free loopback ones, never the app's default 8765 nor the default hub 7447.
"""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
import threading

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the foxglove extra is not installed")

import websocket  # noqa: E402
from foxglove_client import SUBPROTOCOL, FoxgloveClient  # noqa: E402
from service_processes import (  # noqa: E402
    REPO_ROOT,
    free_loopback_port,
    taken_loopback_port,
    until,
)
from up_processes import UpProcess  # noqa: E402

from mapex.exit_codes import EXIT_INTERRUPTED, EXIT_USAGE  # noqa: E402
from mapex.interop.ros_messages import MapFrame  # noqa: E402
from mapex.interop.topics import TF_STATIC_TOPIC, RunTopics  # noqa: E402
from services.bridges import foxglove_live  # noqa: E402
from services.bridges.foxglove_live import SDK_CLIENT_LOGGER, FoxgloveServer  # noqa: E402
from services.config import FoxgloveConfig  # noqa: E402

DEADLINE_S = 10.0  # one exchange with an in-process server on a shared 2-core machine
START_DEADLINE_S = 120.0  # services.up starts its world and planner before the first step
SESSION_DEADLINE_S = 60.0
SESSIONS = 5
RACE_ROBOTS = 60  # x 4 channels made while a client subscribes to each as it appears
FEED_PAUSE_S = 0.05  # between two rounds of poses
RUN_STEPS = 3000  # the run goes on well past the sessions; it is interrupted after them
CHEAP_RUN = (
    "--method",
    "nearest",
    "--members",
    "none",
    "--set",
    "services.workers_wait_s=1",
)  # fmt: skip  (no torch worker: the planner goes on without predictions)


@pytest.fixture
def server():
    served = FoxgloveServer(port=0)
    yield served
    served.close()


def url(server: FoxgloveServer) -> str:
    return f"ws://127.0.0.1:{server.port}"


def connected(server: FoxgloveServer, **options) -> FoxgloveClient:
    client = FoxgloveClient(url(server), **options)
    assert client.pump(lambda c: c.server_info is not None, DEADLINE_S), "no serverInfo"
    return client


def write_all(server: FoxgloveServer, outgoing: list) -> None:
    for each in outgoing:
        server.write(each)


def test_the_server_speaks_the_sdk_subprotocol_only(server):
    assert foxglove_live.SUBPROTOCOL == SUBPROTOCOL
    accepted = websocket.create_connection(url(server), subprotocols=[SUBPROTOCOL], timeout=5)
    try:
        assert accepted.getsubprotocol() == SUBPROTOCOL
    finally:
        accepted.close()
    with pytest.raises(websocket.WebSocketBadStatusException):  # HTTP 400
        websocket.create_connection(url(server), subprotocols=["foxglove.websocket.v1"])


def test_a_late_subscriber_gets_the_latched_topics_at_once(server):
    topics = RunTopics("demo", MapFrame(4, 5))
    write_all(server, topics.observed("r0", np.ones((4, 5), np.uint8), 1))
    write_all(server, topics.pose("r0", (1, 1), 2) + topics.transforms("r0", (1, 1), 2))
    with connected(server) as client:
        latched = {"/mapex/demo/r0/map", "/foxglove/mapex/demo/r0/map", TF_STATIC_TOPIC,
                   "/mapex/demo/r0/trajectory"}  # fmt: skip
        assert client.pump(lambda c: latched <= set(c.received_by_topic), DEADLINE_S)
        assert client.received_by_topic["/mapex/demo/r0/pose"] == 0  # volatile: not again
        write_all(server, topics.pose("r0", (1, 2), 3))
        assert client.pump(lambda c: c.received_by_topic["/mapex/demo/r0/pose"], DEADLINE_S)
        assert client.received_by_topic["/mapex/demo/r0/map"] == 1


def test_a_refused_subscription_is_answered_with_the_channel_made_again(server):
    """What the server does when the SDK refuses a subscription (as it may to a channel it
    made while the client was connected): the channel is made again under a new id, the
    client is told, subscribes again and gets the latched map."""
    topics = RunTopics("demo", MapFrame(4, 5))
    write_all(server, topics.observed("r0", np.ones((4, 5), np.uint8), 1))
    topic = "/mapex/demo/r0/map"
    with connected(server) as client:
        assert client.pump(lambda c: c.received_by_topic[topic] == 1, DEADLINE_S)
        old = server.channel_id(topic)
        logging.getLogger(SDK_CLIENT_LOGGER).error(  # the SDK's line, as it logs it
            "Client 127.0.0.1:1 attempted to subscribe to unknown channel: %d", old
        )
        write_all(server, topics.pose("r0", (1, 1), 2))  # the next write remakes it
        new = server.channel_id(topic)
        assert new != old and server.topics().count(topic) == 1
        assert client.pump(lambda c: old in c.unadvertised and c.received[new] == 1, DEADLINE_S)
        assert server.remake_refused() == []  # once


def test_channels_made_while_a_client_subscribes_to_each_all_deliver(server):
    """Channels made one after another while a client subscribes to each as it is
    advertised (then a pose per robot every round): every topic delivers, and every
    subscription the SDK refused was answered with the channel made again."""
    topics = RunTopics("demo", MapFrame(4, 5))
    client = connected(server)
    stop = threading.Event()

    def feed() -> None:
        step = 0
        while not stop.is_set():
            step += 1
            for k in range(RACE_ROBOTS):
                write_all(server, topics.pose(f"r{k}", (1, 1 + step % 2), step))
            stop.wait(FEED_PAUSE_S)

    feeder = threading.Thread(target=feed, name="feed")
    feeder.start()
    try:
        expected = 4 * RACE_ROBOTS  # pose and trajectory, ROS and Foxglove
        delivered = client.pump(lambda c: len(c.received_by_topic) == expected, 6 * DEADLINE_S)
        assert delivered, f"silent: {client.silent_topics()[:10]}"
        assert set(client.refused_channels()) <= set(client.unadvertised)
    finally:
        stop.set()
        feeder.join()
        client.close()


def test_clients_beyond_the_cap_get_503_and_a_slow_handshake_is_closed():
    """The relay in front of the SDK's server: `max_clients` at once (one more is answered
    503), a handshake that has not arrived in `handshake_timeout_s` closed; each freed
    slot serves again."""
    config = FoxgloveConfig(port=0, max_clients=2, handshake_timeout_s=0.5)
    capped = FoxgloveServer(port=0, config=config)
    try:
        first, second = connected(capped), connected(capped)
        with pytest.raises(websocket.WebSocketBadStatusException) as refused:
            websocket.create_connection(url(capped), subprotocols=[SUBPROTOCOL], timeout=5)
        assert refused.value.status_code == 503
        first.close()
        until(lambda: capped.relay.slots.in_use == 1, "the closed client's slot to be free")
        with socket.create_connection(("127.0.0.1", capped.port), timeout=DEADLINE_S) as slow:
            slow.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # and no more
            assert slow.recv(1024) == b""  # closed unanswered
        assert capped.relay.timed_out == 1
        until(lambda: capped.relay.slots.in_use == 1, "the slow client's slot to be free")
        with connected(capped) as third:
            assert third.server_info["name"] == "mapex"
        second.close()
    finally:
        capped.close()


def test_every_channel_of_a_real_run_delivers_in_five_sessions_in_a_row(tmp_path):
    """services.up --foxglove: five client sessions one after another (the first from
    before the run's first topic, so its channels are made while it is connected) each
    subscribe to every channel advertised, later ones too, and get a message of each."""
    port, endpoint = free_loopback_port(), f"tcp/127.0.0.1:{free_loopback_port()}"
    up = UpProcess(
        tmp_path / "up.log", "--foxglove", str(port), "--listen", endpoint, "--run-prefix",
        "fox", "--out", str(tmp_path / "runs"), "--steps", str(RUN_STEPS), *CHEAP_RUN,
    )  # fmt: skip
    # a session lasts until these delivered, and every other channel advertised so far
    required = [f"{root}/mapex/fox_0/r0/{name}" for root in ("", "/foxglove")
                for name in ("pose", "map", "plan")]  # fmt: skip
    try:
        for session in range(SESSIONS):
            client = until(
                lambda: _running(up) and _connect(port), "the Foxglove server", START_DEADLINE_S
            )
            with client:
                done = client.pump(
                    lambda c: (
                        all(c.received_by_topic[t] for t in required) and not c.silent_topics()
                    ),
                    SESSION_DEADLINE_S,
                )
                silent = client.silent_topics()
                assert done, f"session {session}: {silent} silent\n{up.log()}"
                # a refused subscription was answered with the channel made again
                assert set(client.refused_channels()) <= set(client.unadvertised), session
        assert up.process.poll() is None, f"the run ended before the sessions:\n{up.log()}"
        up.interrupt()
        assert up.wait() == EXIT_INTERRUPTED, up.log()
    finally:
        up.kill()
    assert "Traceback" not in up.log()


def test_a_busy_foxglove_port_is_one_line_and_exit_2_before_any_child(tmp_path):
    with taken_loopback_port() as port:
        done = subprocess.run(
            [sys.executable, "-m", "services.up", "--foxglove", str(port), "--steps", "1",
             "--listen", f"tcp/127.0.0.1:{free_loopback_port()}", "--out", str(tmp_path)],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=START_DEADLINE_S,
        )  # fmt: skip
    assert done.returncode == EXIT_USAGE, done.stderr
    assert done.stderr.splitlines() == [
        f"services.up: error: --foxglove: cannot serve on 127.0.0.1 port {port}: "
        "Address already in use"
    ]
    assert "started" not in done.stdout + done.stderr  # no child process


def test_the_command_refuses_a_taken_port_and_a_bad_one_in_one_line(hub):
    with taken_loopback_port() as port:
        done = subprocess.run(
            [sys.executable, "-m", "services.foxglove", "--port", str(port), "--connect", hub[1]],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=START_DEADLINE_S,
        )  # fmt: skip
    assert done.returncode == EXIT_USAGE, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert f"--foxglove: cannot serve on 127.0.0.1 port {port}: Address already in use" in last
    assert "Traceback" not in done.stderr
    with pytest.raises(SystemExit) as bad:
        foxglove_live.run_cli(["--port", "70000"])
    assert bad.value.code == EXIT_USAGE


def _connect(port: int) -> FoxgloveClient | None:
    try:
        return FoxgloveClient(f"ws://127.0.0.1:{port}")
    except OSError:  # not listening yet (ConnectionRefusedError)
        return None


def _running(up: UpProcess) -> bool:
    """True while the run goes on; fails the test at once with up's log if it ended."""
    if up.process.poll() is not None:
        pytest.fail(f"services.up exited with {up.process.returncode}:\n{up.log()}")
    return True
