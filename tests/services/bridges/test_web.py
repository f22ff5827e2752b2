"""The browser view: pure encoding, throttling and state; a view served from this process
over HTTP on a loopback port (a real Zenoh session, the hub fixture); the command line; then a
real `services.up` run drawn live by headless Chromium (skipped without Debian's Chromium).

Every process and browser is killed at teardown whatever happens; ports are free loopback
ones, never the default hub 7447 nor the view's default 8000.
"""

from __future__ import annotations

import base64
import http.client
import json
import logging
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from service_processes import (
    REPO_ROOT,
    STOP_DEADLINE_S,
    ServiceProcesses,
    free_loopback_port,
    read_until_closed,
    taken_loopback_port,
    until,
)
from up_processes import UpProcess

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.worlds import load_world
from services.bridges.follow import Update
from services.bridges.gate import BUSY_RESPONSE
from services.bridges.web import WebView, check_host, host_header_allowed, is_loopback_host, run_cli
from services.bridges.web_state import (
    EventClient,
    MapThrottle,
    ViewState,
    encode_update,
    final_event,
    frame_key,
    sse_frame,
)
from services.config import WebConfig
from services.keys import robot_key, run_key
from services.messages import (
    FrontiersMessage,
    GoalMessage,
    MapMessage,
    MetricsMessage,
    PathMessage,
    PoseMessage,
    StatusMessage,
    WorldInfo,
)

SHAPE = (30, 40)
START_DEADLINE_S = 60.0  # a cold interpreter (zenoh, numpy) on a shared 2-core machine
READ_TIMEOUT_S = 10.0  # one read of an event stream (keep-alives come far more often)
EVENT_DEADLINE_S = 10.0
FAST = WebConfig(port=0, keepalive_s=0.3, flush_poll_s=0.02)
SERVING = re.compile(r"serving (http://\S+)")
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
CHROMIUM_FLAGS = (
    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--window-size=1200,1000",
)  # fmt: skip
UP_STEPS = 1000  # the run goes on well past the checks; it is killed after them
UP_FIRST_STEP_DEADLINE_S = 150.0  # up starts four torch workers before the first step
ADVANCE_DEADLINE_S = 30.0
OBSERVED_SELECTOR = 'canvas[data-run="{run}"][data-robot="r0"][data-kind="{kind}"]'
SHORT_RUN_STEPS = 600  # metrics every 50 steps, TU every 100: several of each, then the end
LIVE_CHECKS = 3  # times the page's metrics are compared with the view's while the run goes on
RECONNECT_TRIES_S = 3.0  # several of the page's reconnection tries (WebConfig.retry_ms 1 s)
ROUND_MULTIPLES = (1, 2, 5)  # a scale bar's length: one of these times a power of ten
MIN_FRONTIER_RADIUS_CSS_PX = 5.0
WHITE_RGB, GREY_RGB = 0xFFFFFF, 0x808080  # free and unknown cells on the page


def _update(topic: str, message, run: str = "demo", robot: str | None = "r0") -> Update:
    return Update(run, robot, topic, message)


def _observed(t: int, code=FREE, shape=SHAPE) -> MapMessage:
    codes = np.full(shape, UNKNOWN, np.uint8)
    codes[: shape[0] // 2] = code
    return MapMessage(t, "observed", codes)


def _world_info(shape=SHAPE) -> WorldInfo:
    return WorldInfo("tiny", shape, 0.1, np.array([[1, 2]], np.int32))


def _view(session, **overrides) -> WebView:
    config = FAST if not overrides else WebConfig(**{**FAST.__dict__, **overrides})
    return WebView(session, None, config)


# ---------------------------------------------------------------------- pure: events


def test_map_events_carry_the_uint8_bytes_row_major_with_their_size():
    observed = _observed(7, OCCUPIED)
    observed.map_u8[0, 1] = FREE  # row 0, column 1: tells rows from columns
    event = encode_update(_update("observed_map", observed))
    assert event["width"] == SHAPE[1] and event["height"] == SHAPE[0]
    assert {k: event[k] for k in ("run", "robot", "topic", "t", "kind")} == {
        "run": "demo", "robot": "r0", "topic": "observed_map", "t": 7, "kind": "observed"
    }  # fmt: skip
    codes = np.frombuffer(base64.b64decode(event["data"]), np.uint8).reshape(SHAPE)
    np.testing.assert_array_equal(codes, observed.map_u8)
    mean = MapMessage.from_probabilities(3, "mean", np.linspace(0, 1, 1200).reshape(SHAPE))
    quantised = base64.b64decode(encode_update(_update("prediction/mean", mean))["data"])
    assert quantised == mean.map_u8.tobytes()  # q / 255, as the planner sent it


def test_every_other_topic_is_plain_json_with_nulls_for_what_is_missing():
    frontiers = FrontiersMessage(4, np.array([[1, 2], [3, 4]]), np.array([0.5, np.nan]))
    updates = [
        _update("pose", PoseMessage(4, (5, 6))),
        _update("frontiers", frontiers),
        _update("goal", GoalMessage(4, None)),
        _update("path", PathMessage(4, np.array([[5, 6], [1, 2]]))),
        _update("status", StatusMessage(4, "running", "mapex on tiny")),
        _update("metrics", MetricsMessage(4, 0.25, 0.5, None, True)),
        _update("world_info", _world_info(), robot=None),
    ]  # fmt: skip
    events = [json.loads(json.dumps(encode_update(u), allow_nan=False)) for u in updates]
    pose, frontiers, goal, path, status, metrics, world = events
    assert pose["pose"] == [5, 6] and pose["t"] == 4
    assert frontiers["cells"] == [[1, 2], [3, 4]] and frontiers["scores"] == [0.5, None]
    assert goal["goal"] is None and path["cells"] == [[5, 6], [1, 2]]
    assert status["state"] == "running" and status["detail"] == "mapex on tiny"
    assert metrics == {
        "run": "demo", "robot": "r0", "topic": "metrics", "t": 4, "coverage": 0.25,
        "iou": 0.5, "tu": None, "degraded": True,
    }  # fmt: skip
    assert world["robot"] is None and world["shape"] == list(SHAPE) and "t" not in world


def test_an_sse_frame_is_one_named_event_with_one_data_line():
    frame = sse_frame("update", {"detail": "two\nlines", "t": 1}).decode()
    lines = frame.split("\n")
    assert lines[0] == "event: update" and lines[1].startswith("data: ")
    assert frame.endswith("\n\n") and len(lines) == 4
    assert json.loads(lines[1][len("data: ") :]) == {"detail": "two\nlines", "t": 1}


# ---------------------------------------------------------------------- pure: throttle, state


def test_the_throttle_sends_one_map_per_interval_and_always_the_newest():
    throttle = MapThrottle(min_interval_s=0.5)
    maps = [_update("observed_map", _observed(t)) for t in range(4)]
    assert throttle.offer(maps[0], now_s=10.0) is maps[0]
    assert throttle.offer(maps[1], now_s=10.1) is None
    assert throttle.offer(maps[2], now_s=10.2) is None  # replaces maps[1]
    assert throttle.due(now_s=10.4) == [] and throttle.held() == 1
    assert throttle.due(now_s=10.5) == [maps[2]] and throttle.held() == 0
    assert throttle.offer(maps[3], now_s=10.6) is None  # the interval runs from 10.5
    assert throttle.due(now_s=11.0) == [maps[3]]


def test_the_throttle_counts_each_robot_and_map_kind_apart():
    throttle = MapThrottle(min_interval_s=1.0)
    mean = MapMessage.from_probabilities(1, "mean", np.zeros(SHAPE))
    for update in (
        _update("observed_map", _observed(1)),
        _update("prediction/mean", mean),
        _update("observed_map", _observed(1), robot="r1"),
        _update("observed_map", _observed(1), run="other"),
    ):
        assert throttle.offer(update, now_s=0.0) is update


def test_the_state_ignores_older_messages_and_keeps_metric_and_pose_histories():
    state = ViewState(WebConfig(max_metric_points=2), followed_run=None)
    assert state.apply(_update("pose", PoseMessage(5, (1, 1))))
    assert not state.apply(_update("pose", PoseMessage(4, (9, 9))))  # a late reply
    for t, pose in ((6, (1, 1)), (7, (1, 2)), (8, (2, 2))):
        assert state.apply(_update("pose", PoseMessage(t, pose)))
    for t in (0, 50, 50, 100):  # a repeated sample (late reply and live) is kept once
        state.apply(_update("metrics", MetricsMessage(t, t / 200, 0.5, None, False)))
    robot = state.runs["demo"].robots["r0"]
    assert list(robot.trajectory) == [(1, 1), (1, 2), (2, 2)]
    assert [m["t"] for m in robot.metrics_history] == [50, 100]  # bounded by max_metric_points
    assert robot.t == 100 and robot.latest["pose"].message.t == 8


def test_the_snapshot_is_json_of_everything_known_and_old_runs_are_forgotten():
    state = ViewState(WebConfig(max_runs=2), followed_run="b")
    state.apply(_update("world_info", _world_info(), run="a", robot=None))
    state.apply(_update("observed_map", _observed(3), run="a"))
    state.apply(_update("goal", GoalMessage(3, (1, 2)), run="b", robot="r1"))
    snapshot = json.loads(json.dumps(state.snapshot(), allow_nan=False))
    assert snapshot["followed_run"] == "b" and set(snapshot["runs"]) == {"a", "b"}
    run_a = snapshot["runs"]["a"]
    assert run_a["world"]["shape"] == list(SHAPE)
    assert run_a["robots"]["r0"]["latest"]["observed_map"]["width"] == SHAPE[1]
    assert run_a["robots"]["r0"]["t"] == 3 and run_a["robots"]["r0"]["trajectory"] == []
    assert snapshot["runs"]["b"]["robots"]["r1"]["latest"]["goal"]["goal"] == [1, 2]
    assert run_a["final"] is None  # its robot never said finished
    state.apply(_update("pose", PoseMessage(1, (0, 0)), run="c"))
    assert list(state.runs) == ["b", "c"]  # "a" was updated least recently


def _status(t: int, state: str, robot: str = "r0", run: str = "demo") -> Update:
    return _update("status", StatusMessage(t, state), run=run, robot=robot)


def test_a_run_ends_once_every_robot_of_it_said_finished_or_failed():
    state = ViewState()
    assert state.final("demo") is None  # not known at all
    state.apply(_update("world_info", _world_info(), robot=None))
    assert state.final("demo") is None  # no robot yet
    state.apply(_status(0, "running"))
    state.apply(_update("pose", PoseMessage(3, (1, 1)), robot="r1"))  # r1: no status yet
    state.apply(_status(300, "finished"))
    assert state.final("demo") is None
    state.apply(_status(5, "running", robot="r1"))
    assert state.final("demo") is None
    state.apply(_status(280, "finished", robot="r1"))
    assert state.final("demo") == {"state": "finished", "t": 300}  # the latest step of them
    assert state.snapshot()["runs"]["demo"]["final"] == {"state": "finished", "t": 300}
    state.apply(_status(290, "failed", robot="r1"))
    assert state.final("demo") == {"state": "failed", "t": 300}  # any failed: failed
    state.apply(_update("pose", PoseMessage(1, (2, 2)), robot="r2"))  # a robot joined late
    assert state.final("demo") is None
    assert final_event("demo", None) == {"run": "demo", "final": None}


def test_the_view_sends_a_final_event_after_the_status_that_ended_the_run(hub):
    with _view(hub[0]) as view:
        client, snapshot = view.subscribe()
        assert b"event: snapshot" in snapshot
        view.on_update(_status(0, "running", run="web_end"))
        view.on_update(_status(120, "finished", run="web_end"))
        view.on_update(_status(120, "finished", run="web_end"))  # a repeat: no second final
        frames = [client.next_frame(0.01) for _ in range(5)]
        view.unsubscribe(client)
    assert frames[4] == b": keep-alive\n\n"  # nothing more: the repeat changed nothing
    events = [
        (frame.split(b"\n")[0].decode(), json.loads(frame.split(b"\n")[1][len(b"data: ") :]))
        for frame in frames[:4]
    ]
    names = [name for name, _ in events]
    assert names == ["event: update", "event: update", "event: final", "event: update"]
    assert events[1][1]["state"] == "finished" and events[1][1]["t"] == 120
    assert events[2][1] == {"run": "web_end", "final": {"state": "finished", "t": 120}}


def test_an_event_client_sends_keepalives_and_closes_when_too_far_behind():
    client = EventClient(max_queued_events=2)
    assert client.next_frame(timeout_s=0.01) == b": keep-alive\n\n"
    assert client.push(b"one") and client.push(b"two")
    assert not client.push(b"three") and client.closed  # a stalled browser is let go
    assert client.next_frame(timeout_s=0.01) is None
    other = EventClient(max_queued_events=2)
    other.push(b"one")
    assert other.next_frame(0.01) == b"one"
    other.close()
    assert other.next_frame(0.01) is None and not other.push(b"late")
    closing = EventClient(max_queued_events=2)
    closing.push(b"last words")
    closing.close(drain=True)  # the view closes: what is queued still goes out
    assert not closing.push(b"late") and closing.next_frame(0.01) == b"last words"
    assert closing.next_frame(0.01) is None


def test_an_event_client_keeps_the_newest_map_of_each_robot_and_kind_and_every_other_frame():
    """The drop-latest queue: a newer map of a robot and kind replaces the one still queued
    (queued last, the others keep their order); a pose or status is never dropped; past
    its bytes (or frames) the client is closed, bounded whether or not it is read."""
    client = EventClient(max_queued_events=10, max_queued_bytes=100)
    observed = frame_key(_update("observed_map", _observed(1)))
    assert observed == ("demo", "r0", "observed_map")
    assert frame_key(_update("pose", PoseMessage(1, (1, 1)))) is None
    assert frame_key(_update("status", StatusMessage(1, "running", ""))) is None
    mean = frame_key(_update("prediction/mean", _observed(1)))
    other_robot = frame_key(_update("observed_map", _observed(1), robot="r1"))
    for frame, key in [(b"map1", observed), (b"pose1", None), (b"mean1", mean),
                       (b"map1r1", other_robot), (b"map2", observed), (b"pose2", None),
                       (b"map3", observed)]:  # fmt: skip
        assert client.push(frame, key)
    queued = [client.next_frame(0.01) for _ in range(len(client))]
    assert queued == [b"pose1", b"mean1", b"map1r1", b"pose2", b"map3"]
    assert client.replaced == 2 and client.queued_bytes == 0
    assert client.push(b"x" * 60, observed) and client.push(b"y" * 39)
    assert client.push(b"z" * 61, observed)  # replaces the 60 bytes: 100 in all
    assert not client.push(b"!") and client.closed  # 101 bytes: let go
    assert client.next_frame(0.01) is None and client.queued_bytes == 0


@pytest.mark.parametrize(
    "host, loopback",
    [("127.0.0.1", True), ("127.3.2.1", True), ("::1", True), ("[::1]", True),
     ("localhost", True), ("LOCALHOST", True), ("0.0.0.0", False), ("192.168.1.20", False),
     ("::", False), ("example.com", False), ("", False)],
)  # fmt: skip
def test_only_loopback_hosts_are_served_without_allow_remote(host, loopback):
    assert is_loopback_host(host) is loopback
    check_host(host, allow_remote=True)
    if loopback:
        check_host(host, allow_remote=False)
    else:
        with pytest.raises(ValueError, match="add --allow-remote"):
            check_host(host, allow_remote=False)


def test_requests_naming_another_host_are_refused_unless_remote_is_allowed():
    for header in ("127.0.0.1:8765", "localhost:8765", "[::1]:8765", "localhost"):
        assert host_header_allowed(header, allow_remote=False)
    for header in ("evil.example:8765", "192.168.1.2", "", None):
        assert not host_header_allowed(header, allow_remote=False)
    assert host_header_allowed("evil.example:8765", allow_remote=True)


# ---------------------------------------------------------------------- a view in this process


class EventStream:
    """An `/events` stream read as the page reads it (the stand-in for a browser)."""

    def __init__(self, port: int, timeout_s: float = READ_TIMEOUT_S) -> None:
        self.connection = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout_s)
        self.connection.request("GET", "/events")
        self.response = self.connection.getresponse()
        assert self.response.status == 200
        assert self.response.getheader("Content-Type") == "text/event-stream"

    def next_event(self, deadline_s: float | None = None) -> tuple[str, dict]:
        """The next (event name, data), skipping keep-alive comments and the retry field;
        fails the test at `deadline_s` (monotonic; default EVENT_DEADLINE_S from now)."""
        deadline_s = deadline_s or time.monotonic() + EVENT_DEADLINE_S
        name, data = "message", None
        while time.monotonic() < deadline_s:  # keep-alives come every FAST.keepalive_s
            line = self.response.readline().decode()
            if not line:
                raise EOFError("the stream ended")
            line = line.rstrip("\n")
            if not line and data is not None:
                return name, json.loads(data)
            field, _, value = line.partition(": ")
            if field == "event":
                name = value
            elif field == "data":
                data = value
        pytest.fail("timed out waiting for an event")

    def wait_for(self, what: str, *matchers, deadline_s: float = EVENT_DEADLINE_S) -> list:
        """Every event read until each of `matchers(name, data)` matched one, in any order."""
        deadline, seen, pending = time.monotonic() + deadline_s, [], list(matchers)
        while pending:
            if time.monotonic() >= deadline:
                topics = [(name, data.get("topic"), data.get("t")) for name, data in seen]
                pytest.fail(f"timed out waiting for {what}; saw {topics}")
            seen.append(self.next_event(deadline))
            pending = [matches for matches in pending if not matches(*seen[-1])]
        return seen

    def close(self) -> None:
        self.connection.close()


@pytest.fixture
def view(hub):
    with _view(hub[0]) as started:
        yield started


def _get(url: str, host: str | None = None) -> tuple[int, str, bytes]:
    request = urllib.request.Request(url, headers={"Host": host} if host else {})
    try:
        with urllib.request.urlopen(request, timeout=READ_TIMEOUT_S) as response:
            return response.status, response.headers["Content-Type"], response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.headers["Content-Type"], error.read()


def _is_update(topic: str, t: int | None = None, run: str | None = None):
    def matches(name: str, data: dict) -> bool:
        return (
            name == "update"
            and data["topic"] == topic
            and (t is None or data.get("t") == t)
            and (run is None or data["run"] == run)
        )

    return matches


def _known_in_state(url: str, run: str, robot: str = "r0") -> set[str]:
    """The topics the view at `url` knows of `robot` of `run` ("world_info" for the run's)."""
    known = json.loads(_get(url + "state")[2])["runs"].get(run, {})
    topics = set(known.get("robots", {}).get(robot, {}).get("latest", {}))
    return topics | ({"world_info"} if known.get("world") else set())


def test_the_page_its_files_and_the_state_are_served(view):
    status, content_type, page = _get(view.url)
    assert status == 200 and content_type.startswith("text/html")
    assert b'src="app.js"' in page and b'href="style.css"' in page and b"://" not in page
    for name, kind in (("app.js", "text/javascript"), ("style.css", "text/css")):
        status, content_type, body = _get(view.url + name)
        assert status == 200 and content_type.startswith(kind) and len(body) > 1000
        assert b"://" not in body  # nothing is fetched from elsewhere: it works offline
    status, content_type, body = _get(view.url + "state")
    assert status == 200 and content_type == "application/json"
    assert json.loads(body)["followed_run"] is None
    assert _get(view.url + "nothing")[0] == 404
    assert _get(view.url + "state", host="evil.example")[0] == 403  # DNS rebinding


def test_a_late_page_gets_the_snapshot_then_every_update(hub, view):
    session, run = hub[0], "web_live"
    session.put(run_key(run, "world_info"), _world_info().encode())
    session.put(robot_key(run, "r0", "observed_map"), _observed(2).encode())
    session.put(robot_key(run, "r0", "pose"), PoseMessage(2, (3, 4)).encode())
    wanted = {"world_info", "observed_map", "pose"}  # they may arrive in any order
    until(lambda: wanted <= _known_in_state(view.url, run), "all three in /state")
    stream = EventStream(view.port)
    try:
        name, snapshot = stream.next_event()
        assert name == "snapshot"
        known = snapshot["runs"][run]
        assert known["world"]["name"] == "tiny"
        assert known["robots"]["r0"]["latest"]["observed_map"]["t"] == 2
        assert known["robots"]["r0"]["trajectory"] == [[3, 4]]
        session.put(robot_key(run, "r0", "pose"), PoseMessage(3, (3, 5)).encode())
        session.put(robot_key(run, "r1", "status"), StatusMessage(3, "running").encode())
        stream.wait_for(
            "the new pose and the teammate's status",
            _is_update("pose", 3, run),
            _is_update("status", 3, run),
        )
    finally:
        stream.close()


def test_malformed_payloads_on_the_run_keys_do_not_break_the_stream(hub, view, caplog):
    session, run = hub[0], "web_bad"
    stream = EventStream(view.port)
    try:
        assert stream.next_event()[0] == "snapshot"
        rng = np.random.default_rng(0)
        with caplog.at_level(logging.WARNING, logger="services.follow"):
            for topic in ("observed_map", "pose", "status", "metrics"):
                session.put(robot_key(run, "r0", topic), rng.bytes(64))
            session.put(robot_key(run, "r0", "observed_map"), PoseMessage(1, (1, 1)).encode())
            session.put(robot_key(run, "r0", "pose"), PoseMessage(5, (1, 1)).encode())
            seen = stream.wait_for("the good pose after the junk", _is_update("pose", 5, run))
            until(lambda: caplog.text.count("dropped a message on") >= 5, "five drops logged")
        assert [data["topic"] for _, data in seen if data.get("run") == run] == ["pose"]
        assert f"dropped a message on {robot_key(run, 'r0', 'observed_map')}" in caplog.text
        session.put(robot_key(run, "r0", "observed_map"), _observed(6).encode())
        stream.wait_for("a good map after the junk", _is_update("observed_map", 6, run))
    finally:
        stream.close()


def test_maps_are_throttled_and_the_newest_always_arrives(hub):
    session, run, rate_per_s = hub[0], "web_fast", 2.0
    with _view(session, map_events_per_s=rate_per_s) as view:
        stream = EventStream(view.port)
        try:
            stream.next_event()
            started_s = time.monotonic()
            for t in range(1, 21):
                session.put(robot_key(run, "r0", "observed_map"), _observed(t).encode())
                session.put(robot_key(run, "r0", "pose"), PoseMessage(t, (1, t)).encode())
            seen = stream.wait_for(
                "the newest map and pose",
                _is_update("observed_map", 20, run),
                _is_update("pose", 20, run),
            )
            elapsed_s = time.monotonic() - started_s
        finally:
            stream.close()
    maps = [data["t"] for _, data in seen if _is_update("observed_map", run=run)("update", data)]
    poses = [data["t"] for _, data in seen if _is_update("pose", run=run)("update", data)]
    assert poses == list(range(1, 21))  # small messages are never held back
    assert maps[0] == 1 and maps[-1] == 20 and maps == sorted(maps)
    assert len(maps) <= 2 + elapsed_s * rate_per_s  # the first at once, then at most the rate


def test_a_browser_that_goes_away_is_dropped_quietly(hub, view, caplog):
    with caplog.at_level(logging.DEBUG, logger="services.web"):
        with socket.create_connection(("127.0.0.1", view.port), timeout=READ_TIMEOUT_S) as raw:
            raw.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert b"event: snapshot" in _read_until(raw, b"event: snapshot")
            until(lambda: view.clients == 1, "the stream to be counted")
        until(lambda: view.clients == 0, "the closed stream to be dropped")
    web_records = [r for r in caplog.records if r.name == "services.web"]
    assert not [r for r in web_records if r.levelno >= logging.WARNING], caplog.text
    assert "Traceback" not in caplog.text


def _read_until(raw: socket.socket, marker: bytes) -> bytes:
    received = b""
    while marker not in received:
        chunk = raw.recv(65536)
        if not chunk:
            break
        received += chunk
    return received


def test_a_stalled_browser_is_let_go_and_a_closed_view_ends_every_stream(hub):
    with _view(hub[0], client_max_queued_events=3) as view:
        stalled, _ = view.subscribe()  # never read from
        for t in range(5):
            view.on_update(_update("pose", PoseMessage(t, (1, t)), run="web_stall"))
        assert stalled.closed and view.clients == 0
        listening = EventStream(view.port)
        assert listening.next_event()[0] == "snapshot"
    with pytest.raises((EOFError, ConnectionError)):
        listening.wait_for("the end of the stream", lambda *_: False)
    listening.close()


def test_a_closing_view_still_sends_what_it_queued_then_ends_the_streams(hub):
    with _view(hub[0]) as view:
        stream = EventStream(view.port)
        assert stream.next_event()[0] == "snapshot"
        until(lambda: view.clients == 1, "the stream to be counted")
        view.on_update(_status(40, "finished", run="web_bye"))
    try:  # closed right after the run's last status: the page still learns how it ended
        seen = stream.wait_for(
            "the status and the final event",
            _is_update("status", 40, "web_bye"),
            lambda name, data: name == "final" and data["final"]["t"] == 40,
        )
        assert [name for name, _ in seen] == ["update", "final"]
        with pytest.raises((EOFError, ConnectionError)):
            stream.next_event()
    finally:
        stream.close()


def _partial_request(port: int, head: bytes = b"GET /state HTTP/1.1\r\nHost: 127.0.0.1\r\n"):
    """A connection that sent the start of a request and holds (no blank line after it)."""
    connection = socket.create_connection(("127.0.0.1", port), timeout=READ_TIMEOUT_S)
    connection.sendall(head)
    return connection


def test_the_view_serves_at_most_max_connections_and_answers_one_more_503(hub):
    """Held connections take the view's threads up to `max_connections`; one more is
    answered 503 at once; a freed slot serves again."""
    with _view(hub[0], max_connections=3, request_timeout_s=60.0) as view:
        held = [_partial_request(view.port) for _ in range(3)]
        until(lambda: view.connections.in_use == 3, "the held connections to be served")
        with _partial_request(view.port) as fourth:
            assert read_until_closed(fourth) == BUSY_RESPONSE
        assert view.connections.refused == 1 and view.connections.most == 3
        for connection in held:
            connection.close()
        until(lambda: view.connections.in_use == 0, "the slots to be given back")
        assert _get(view.url + "state")[0] == 200


def test_a_partial_request_is_closed_after_the_request_timeout(hub):
    """A request whose head does not arrive in `request_timeout_s` (even one trickling in,
    a header line at a time) is closed unanswered and its slot freed."""
    with _view(hub[0], max_connections=1, request_timeout_s=0.5) as view:
        began = time.monotonic()
        with _partial_request(view.port) as slow:
            for _ in range(3):
                time.sleep(0.1)
                slow.sendall(b"X-Slow: 1\r\n")
            assert read_until_closed(slow) == b""
        assert time.monotonic() - began < READ_TIMEOUT_S / 2
        until(lambda: view.connections.in_use == 0, "the slot to be given back")
        assert _get(view.url + "state")[0] == 200  # the one slot serves again


def test_a_stream_that_does_not_read_is_let_go_after_the_send_timeout(hub):
    """A browser that takes nothing: the write blocks once the socket buffers are full,
    and `send_timeout_s` later the stream ends and its thread and slot are freed."""
    big = (1000, 1000)  # 1.3 MB per map event
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.settimeout(READ_TIMEOUT_S)
    with stalled, _view(hub[0], send_timeout_s=0.5, client_max_queued_bytes=2**30) as view:
        stalled.connect(("127.0.0.1", view.port))
        stalled.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        until(lambda: view.clients == 1, "the stream to be counted")
        for robot in range(20):  # each robot's first map goes out at once: 26 MB
            view.on_update(_update("observed_map", _observed(1, shape=big), robot=f"r{robot}"))
        until(lambda: view.clients == 0, "the stalled stream to be let go", EVENT_DEADLINE_S)
        until(lambda: view.connections.in_use == 0, "its slot to be given back")


def test_a_host_beyond_loopback_and_a_taken_port_are_refused(hub):
    with pytest.raises(ValueError, match="not a loopback address"):
        WebView(hub[0], None, WebConfig(host="0.0.0.0", port=0))
    with (
        taken_loopback_port() as port,
        pytest.raises(OSError, match=f"cannot serve on 127.0.0.1 port {port}: "),
    ):
        WebView(hub[0], None, WebConfig(port=port))


# ---------------------------------------------------------------------- command line


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--port", "70000"], "'70000' is not a port (0 to 65535)"),
        (["--port", "web"], "'web' is not a port"),
        (["--host", "0.0.0.0"], "--host '0.0.0.0' is not a loopback address"),
        (["--host", "example.com"], "add --allow-remote"),
        (["--run", "Bad Run"], "--run 'Bad Run' must match"),
        (["--run", "alive"], "--run 'alive' must match"),
        (["--map-events-per-s", "0"], "'0' is not a positive number per second"),
        (["--map-events-per-s", "inf"], "'inf' is not a positive number per second"),
    ],
)
def test_bad_flags_are_one_line_errors(flags, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        run_cli(flags)
    assert exit_info.value.code == 2
    errors = capsys.readouterr().err.splitlines()
    assert sum(message in line for line in errors) == 1 and "Traceback" not in "\n".join(errors)


def _web_command(*flags: str) -> list[str]:
    return [sys.executable, "-m", "services.web", *flags]


def test_a_taken_port_is_one_line_and_exit_2_as_a_process(hub):
    with taken_loopback_port() as taken_port:
        port = str(taken_port)
        result = subprocess.run(
            _web_command("--port", port, "--connect", hub[1]),
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=START_DEADLINE_S,
        )  # fmt: skip
    assert result.returncode == 2, result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert f"cannot serve on 127.0.0.1 port {port}" in last and "Traceback" not in result.stderr


def test_the_command_serves_on_a_free_port_and_stops_on_sigint(hub, tmp_path):
    processes = ServiceProcesses(hub[1], tmp_path)
    try:
        web = processes.spawn("web", "services.web", "--run", "web_cli", "--port", "0")
        url = _served_url(processes, "web")

        def goal_known() -> bool:  # put again until the view's subscription has reached the hub
            hub[0].put(robot_key("web_cli", "r0", "goal"), GoalMessage(1, (2, 3)).encode())
            return "goal" in _known_in_state(url, "web_cli")

        until(goal_known, "the goal in /state", EVENT_DEADLINE_S)
        web.send_signal(signal.SIGINT)
        assert web.wait(STOP_DEADLINE_S) == 0
    finally:
        processes.kill_all()
    log = processes.log_of("web")
    assert "following run web_cli" in log and "Traceback" not in log


def _served_url(processes: ServiceProcesses, name: str) -> str:
    """The URL a `services.web` process logged it serves (it picked a free port)."""
    found = []

    def announced() -> bool:
        found[:] = SERVING.findall(processes.log_of(name))
        return bool(found)

    processes.wait_until_announced(name, announced, START_DEADLINE_S)
    return found[0]


# ---------------------------------------------------------------------- a real run in Chromium


def _headless_chromium(profile_dir: Path):
    """Debian's Chromium driven by Selenium, headless, with the flags this machine needs."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile_dir}"):
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=Service(str(CHROMEDRIVER)))


def _canvas_facts(driver, selector: str) -> dict | None:
    """The canvas's size, data-t and, once painted, a summary of its pixels (or None)."""
    return driver.execute_script(
        """
        const canvas = document.querySelector(arguments[0]);
        if (!canvas) return null;
        const facts = {width: canvas.width, height: canvas.height,
                       t: canvas.dataset.t === undefined ? null : Number(canvas.dataset.t),
                       painted: canvas.dataset.mapT !== undefined};
        if (!facts.painted) return facts;
        const pixels = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
        const colours = new Set();
        let opaque = 0;
        for (let i = 0; i < pixels.length; i += 4) {
          if (pixels[i + 3] === 255) opaque++;
          colours.add((pixels[i] << 16) | (pixels[i + 1] << 8) | pixels[i + 2]);
        }
        return {...facts, opaque, colours: [...colours].slice(0, 64)};
        """,
        selector,
    )


def _step_shown(driver, selector: str) -> int | None:
    facts = _canvas_facts(driver, selector)
    return None if facts is None else facts["t"]


@pytest.mark.slow
@pytest.mark.skipif(
    not (CHROMIUM.exists() and CHROMEDRIVER.exists()),
    reason="needs Debian's /usr/bin/chromium and /usr/bin/chromedriver "
    "(apt-get install chromium chromium-driver)",
)
def test_a_real_run_is_drawn_live_in_headless_chromium(tmp_path):
    endpoint, run = f"tcp/127.0.0.1:{free_loopback_port()}", "web-0"
    rows, cols = load_world("default").shape
    up = UpProcess(
        tmp_path / "up.log", "--world", "default", "--listen", endpoint, "--run-prefix", "web",
        "--out", str(tmp_path / "runs"), "--method", "mapex", "--steps", str(UP_STEPS),
    )  # fmt: skip
    processes = ServiceProcesses(endpoint, tmp_path)
    driver = None
    try:
        web = processes.spawn("web", "services.web", "--run", run, "--port", "0")
        url = _served_url(processes, "web")
        driver = _headless_chromium(tmp_path / "chromium")
        driver.get(url)
        observed = OBSERVED_SELECTOR.format(run=run, kind="observed")
        first_t = until(
            lambda: _running(up) and _step_shown(driver, observed),
            "the page to show a step of the run",
            UP_FIRST_STEP_DEADLINE_S,
        )
        facts = _canvas_facts(driver, observed)
        assert (facts["width"], facts["height"]) == (cols, rows)  # one canvas pixel per cell
        _put_junk(endpoint, run, processes)
        later_t = until(
            lambda: (
                (_step_shown(driver, observed) or 0) > first_t and _step_shown(driver, observed)
            ),
            "the page's step to advance after malformed payloads",
            ADVANCE_DEADLINE_S,
        )
        facts = _canvas_facts(driver, observed)
        assert facts["painted"] and facts["opaque"] == rows * cols
        assert {WHITE_RGB, GREY_RGB} <= set(facts["colours"])  # free and unknown cells drawn
        mean = OBSERVED_SELECTOR.format(run=run, kind="mean")
        until(lambda: _canvas_facts(driver, mean)["painted"], "the mean prediction", 30)
        assert up.process.poll() is None, f"the run ended early (t = {later_t}):\n{up.log()}"
        web.send_signal(signal.SIGINT)
        assert web.wait(STOP_DEADLINE_S) == 0
    finally:
        if driver is not None:
            driver.quit()
        processes.kill_all()
        up.kill()
    assert "Traceback" not in processes.log_of("web")


def _running(up: UpProcess) -> bool:
    """True while the run goes on; fails the test at once with up's log if it ended."""
    if up.process.poll() is not None:
        pytest.fail(f"services.up exited with {up.process.returncode}:\n{up.log()}")
    return True


def _put_junk(endpoint: str, run: str, processes: ServiceProcesses) -> None:
    """Random bytes on the run's keys from another session, until the view logs a drop."""
    from services.zenoh_config import open_session, zenoh_config

    session = open_session(zenoh_config(connect=[endpoint], listen=[]))
    rng = np.random.default_rng(1)
    try:

        def dropped() -> bool:
            for topic in ("observed_map", "pose", "metrics"):
                session.put(robot_key(run, "r0", topic), rng.bytes(64))
            return "dropped a message on" in processes.log_of("web")

        until(dropped, "the view to drop the malformed payloads", EVENT_DEADLINE_S)
    finally:
        session.close()


# ---------------------------------------------------------------------- a short run to its end


PAGE_FACTS = """
const robot = `[data-run="${arguments[0]}"][data-robot="r0"]`;
const data = (selector) => ({...(document.querySelector(selector)?.dataset || {})});
const badge = document.getElementById("connection");
return {metrics: data(`canvas${robot}[data-kind="metrics"]`),
        overlay: data(`canvas${robot}[data-kind="overlay"]`),
        run: data(`section.run[data-run="${arguments[0]}"]`),
        connection: {state: badge.dataset.state, text: badge.textContent}};
"""


def _page(driver, run: str) -> dict:
    """What the page shows of `run`'s robot r0: its data-* hooks (docs/protocol.md)."""
    return driver.execute_script(PAGE_FACTS, run)


def _robot_state(url: str, run: str) -> dict:
    return json.loads(_get(url + "state")[2])["runs"][run]["robots"]["r0"]


def _check_shown_metrics(driver, url: str, run: str) -> None:
    """The page shows the latest metrics message the view has (or a newer one) within a
    short wait, with the coverage of that sample."""
    latest = _robot_state(url, run)["latest"]["metrics"]
    until(
        lambda: int(_page(driver, run)["metrics"].get("coverageT", -1)) >= latest["t"],
        f"the page to show the metrics of t = {latest['t']}",
        EVENT_DEADLINE_S,
    )
    shown = _page(driver, run)["metrics"]
    samples = {m["t"]: m for m in _robot_state(url, run)["metrics_history"]}
    assert float(shown["coverage"]) == samples[int(shown["coverageT"])]["coverage"], shown


@pytest.mark.slow
@pytest.mark.skipif(
    not (CHROMIUM.exists() and CHROMEDRIVER.exists()),
    reason="needs Debian's /usr/bin/chromium and /usr/bin/chromedriver",
)
def test_a_short_run_is_shown_to_its_end_in_headless_chromium(tmp_path):
    endpoint, run = f"tcp/127.0.0.1:{free_loopback_port()}", "webend-0"
    up = UpProcess(
        tmp_path / "up.log", "--world", "default", "--listen", endpoint, "--run-prefix",
        "webend", "--out", str(tmp_path / "runs"), "--steps", str(SHORT_RUN_STEPS),
    )  # fmt: skip
    processes = ServiceProcesses(endpoint, tmp_path)
    driver = None
    try:
        web = processes.spawn("web", "services.web", "--run", run, "--port", "0")
        url = _served_url(processes, "web")
        driver = _headless_chromium(tmp_path / "chromium")
        driver.get(url)
        until(
            lambda: up.process.poll() is not None or "coverageT" in _page(driver, run)["metrics"],
            "the page to show a metric sample",
            UP_FIRST_STEP_DEADLINE_S,
        )
        for _ in range(LIVE_CHECKS):  # while the run goes on (it may be over already)
            if up.process.poll() is None:
                _check_shown_metrics(driver, url, run)
        assert up.wait() == 0, up.log()
        final = until(lambda: json.loads(_get(url + "state")[2])["runs"][run]["final"], "final")
        assert final == {"state": "finished", "t": SHORT_RUN_STEPS}
        until(lambda: _page(driver, run)["run"]["state"] == "finished", "the run shown ended")
        page = _page(driver, run)
        assert page["run"]["finalT"] == str(SHORT_RUN_STEPS)
        assert page["connection"] == {"state": "ended", "text": "finished"}
        _check_shown_metrics(driver, url, run)
        assert page["metrics"]["coverageT"] == str(SHORT_RUN_STEPS)  # the last sample

        history = _robot_state(url, run)["metrics_history"]
        tu_known = sum(sample["tu"] is not None for sample in history)
        assert tu_known >= 2  # TU at t = 0, 100, ...: drawn as a line through them
        assert page["metrics"]["tuPoints"] == str(tu_known)
        assert page["metrics"]["tuSegments"] == str(tu_known - 1)

        world = json.loads(_get(url + "state")[2])["runs"][run]["world"]
        overlay = page["overlay"]
        scale_m, scale_cells = float(overlay["scaleM"]), float(overlay["scaleCells"])
        assert scale_cells * world["resolution_m"] == pytest.approx(scale_m)
        assert 0 < scale_cells <= world["shape"][1]  # it fits on the map
        power = 10 ** np.floor(np.log10(scale_m))
        assert any(scale_m == pytest.approx(m * power) for m in ROUND_MULTIPLES)
        assert float(overlay["frontierRadiusCssPx"]) >= MIN_FRONTIER_RADIUS_CSS_PX
        assert int(overlay["frontiers"]) > 0

        web.send_signal(signal.SIGINT)
        assert web.wait(STOP_DEADLINE_S) == 0
        closed = {"state": "closed", "text": "finished (server closed)"}
        until(lambda: _page(driver, run)["connection"] == closed, "the closed server shown")
        time.sleep(RECONNECT_TRIES_S)  # the browser tries to reconnect meanwhile, and fails
        assert _page(driver, run)["connection"] == closed
    finally:
        if driver is not None:
            driver.quit()
        processes.kill_all()
        up.kill()
    assert "Traceback" not in processes.log_of("web")
