"""The outside tools of `services.up` / `services.evaluate` that serve sockets (`--web`,
`--foxglove`) run as supervised children, outside the process whose death ends the run:

* killed, each is restarted and the run finishes as if nothing happened;
* a port already taken is one line, exit 2, before any child starts;
* SOAK (time-bounded, loopback only, under a minute on a busy 2-core machine): a small
  campaign beside 500 slow HTTP clients and 50 Foxglove clients that subscribe to every
  channel and never read ends with the results of the same campaign run alone, while the
  supervisor's memory stays that of the campaign alone and the tools stay bounded.

Ports are free loopback ones, never the defaults (8000, 8765) nor the default hub 7447.
"""

from __future__ import annotations

import json
import os
import re
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

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
from shard_runs import run_records  # noqa: E402
from up_processes import UpProcess, kill_quietly, pid_alive  # noqa: E402

from mapex.exit_codes import EXIT_USAGE  # noqa: E402
from services.bridges.gate import BUSY_RESPONSE  # noqa: E402
from services.config import DEFAULT_FOXGLOVE, DEFAULT_WEB  # noqa: E402

START_DEADLINE_S = 120.0  # a cold interpreter per child on a shared 2-core machine
RUN_DEADLINE_S = 300.0
CHEAP = ("--members", "none", "--set", "services.workers_wait_s=1")  # fmt: skip  (no torch)
UP_STEPS = 2000  # the run goes on while both tools are killed and come back, then ends
_STARTED = re.compile(r"\[supervisor\] started (\S+) \(pid (\d+)\)")

# the soak: 2 short episodes at once, of a method that needs no predictor
SOAK_CAMPAIGN = ("--maps", "generated:0", "--methods", "nearest", "--starts", "0,1",
                 "--steps", "300", "--jobs", "2", *CHEAP)  # fmt: skip
SLOW_HTTP_CLIENTS = 500
NON_READING_FOXGLOVE_CLIENTS = 50
PARTIAL_REQUEST = b"GET /state HTTP/1.1\r\nHost: 127.0.0.1\r\n"  # no blank line: never ends
HTTP_ROUND_S = DEFAULT_WEB.request_timeout_s + 3.0  # a round of slow clients, at most
RSS_EVERY_S = 0.2
STOP_S = 5.0  # for the clients' threads to stop (each waits at most 2 s on a socket)
# what the soaked supervisor may hold beyond the campaign alone: its router's links to the
# two tools (~70 MB measured without any client of theirs), never what their clients cost
# (the in-process tools grew it by GBs)
SUPERVISOR_EXTRA_RSS_BYTES = 128 * 2**20
FOXGLOVE_RSS_BYTES_AT_MOST = 1024 * 2**20  # the Foxglove child, its 7 non-readers at the cap
CAMPAIGNS = ("alone", "soaked")
VOLATILE_METRICS = ("wall_time_s",)  # all else of an episode's metrics.json is reproduced


def _http_get(port: int, path: str = "/state") -> int:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as response:
        return response.status


def _serves_http(port: int) -> bool:
    try:
        return _http_get(port) == 200
    except OSError:
        return False


def _serves_foxglove(port: int) -> bool:
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{port}", subscribe_all=False)
    except (OSError, websocket.WebSocketException):
        return False
    with client:
        return client.pump(lambda c: c.server_info is not None, 10.0)


def _parent_pid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def test_killed_web_and_foxglove_children_come_back_and_the_run_ends_as_usual(tmp_path):
    """`services.up --web --foxglove`: the two tools are child processes of up (not up
    itself); SIGKILLed, each is restarted on its port and serves again, and the run goes on
    to exit 0 with its results."""
    web_port, fox_port = free_loopback_port(), free_loopback_port()
    up = UpProcess(
        tmp_path / "up.log", "--world", "generated:0", "--method", "nearest", *CHEAP,
        "--steps", str(UP_STEPS), "--web", str(web_port), "--foxglove", str(fox_port),
        "--listen", f"tcp/127.0.0.1:{free_loopback_port()}", "--run-prefix", "tools",
        "--out", str(tmp_path / "runs"),
    )  # fmt: skip
    try:
        until(
            lambda: _running(up) and _serves_http(web_port) and _serves_foxglove(fox_port),
            "the web view and the Foxglove server to serve",
            START_DEADLINE_S,
        )
        first = {
            name: until(lambda n=name: up.children().get(n), f"{name}: a child process of up")[0]
            for name in ("web", "foxglove")
        }
        for pid in first.values():
            assert pid != up.process.pid and _parent_pid(pid) == up.process.pid
            os.kill(pid, signal.SIGKILL)
        until(
            lambda: all(len(up.children().get(name, [])) == 2 for name in first),
            "both tools to be restarted",
            START_DEADLINE_S,
        )
        assert up.process.poll() is None, f"the run ended with its tools:\n{up.log()}"
        until(
            lambda: (
                (up.process.poll() is not None)
                or (_serves_http(web_port) and _serves_foxglove(fox_port))
            ),
            "the restarted tools to serve on their ports",
            START_DEADLINE_S,
        )
        assert up.wait(RUN_DEADLINE_S) == 0, up.log()
    finally:
        up.kill()
    log = up.log()
    for name in ("web", "foxglove"):
        assert f"{name} exited with -9 (SIGKILL); restarted (1/" in log, log
    (metrics,) = (tmp_path / "runs").glob("*/metrics.json")
    assert json.loads(metrics.read_text())["steps"] == UP_STEPS
    assert "Traceback" not in log


def _running(up: UpProcess) -> bool:
    """True while the run goes on; fails the test at once with up's log if it ended."""
    if up.process.poll() is not None:
        pytest.fail(f"services.up exited with {up.process.returncode}:\n{up.log()}")
    return True


def test_a_busy_web_port_is_one_line_and_exit_2_before_any_child(tmp_path):
    with taken_loopback_port() as port:
        done = subprocess.run(
            [sys.executable, "-m", "services.up", "--web", str(port), "--steps", "1",
             "--listen", f"tcp/127.0.0.1:{free_loopback_port()}", "--out", str(tmp_path)],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=START_DEADLINE_S,
        )  # fmt: skip
    assert done.returncode == EXIT_USAGE, done.stderr
    assert done.stderr.splitlines() == [
        f"services.up: error: --web: cannot serve on 127.0.0.1 port {port}: Address already in use"
    ]
    assert "started" not in done.stdout + done.stderr  # no child process


# ---------------------------------------------------------------------------- the soak


def _rss_bytes(pid: int) -> int:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return 0
    found = re.search(r"^VmRSS:\s+(\d+) kB", status, flags=re.MULTILINE)
    return int(found.group(1)) * 1024 if found else 0


def _threads(pid: int) -> int:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return 0
    found = re.search(r"^Threads:\s+(\d+)", status, flags=re.MULTILINE)
    return int(found.group(1)) if found else 0


class _Peaks:
    """The largest RSS (and thread count) of each named process, sampled on a thread."""

    def __init__(self, pids: dict[str, Callable[[], int | None]]) -> None:
        self.pids = pids  # name -> a function giving the current pid, or None
        self.rss: dict[str, int] = dict.fromkeys(pids, 0)
        self.threads: dict[str, int] = dict.fromkeys(pids, 0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="rss", daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(RSS_EVERY_S):
            for name, pid_of in self.pids.items():
                if (pid := pid_of()) is not None:
                    self.rss[name] = max(self.rss[name], _rss_bytes(pid))
                    self.threads[name] = max(self.threads[name], _threads(pid))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


class _SlowHttpClients:
    """Rounds of `count` connections that send the start of a request and hold, until
    stopped: each ends refused (answered 503, or closed before its request went out: at
    the cap), closed unanswered (held until the view's request timeout) or unconnected
    (not accepted within 2 s). A connection the view ends well before its request timeout
    was refused (a 503, or a reset)."""

    def __init__(self, port: int, count: int) -> None:
        self.port, self.count = port, count
        self.refused = self.dropped = self.unconnected = self.rounds = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="slow http", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._round()

    def _round(self) -> None:
        """Open up to `count` slow connections, then wait for the view to end each."""
        with selectors.DefaultSelector() as waiting:
            for _ in range(self.count):
                if self._stop.is_set():
                    break
                connection = socket.socket()
                connection.settimeout(2.0)
                try:
                    connection.connect(("127.0.0.1", self.port))
                except ConnectionRefusedError:  # the view stopped: the campaign is over
                    connection.close()
                    self._stop.wait(0.5)
                    break
                except OSError:  # not accepted in time
                    self.unconnected += 1
                    connection.close()
                    continue
                try:
                    connection.sendall(PARTIAL_REQUEST)
                except OSError:  # refused and closed before the request went out
                    self.refused += 1
                    connection.close()
                    continue
                connection.setblocking(False)
                waiting.register(connection, selectors.EVENT_READ, time.monotonic())
            self.rounds += bool(waiting.get_map())
            deadline = time.monotonic() + HTTP_ROUND_S
            while waiting.get_map() and time.monotonic() < deadline and not self._stop.is_set():
                for key, _ in waiting.select(timeout=0.2):
                    self._ended(key.fileobj, time.monotonic() - key.data)
                    waiting.unregister(key.fileobj)
                    key.fileobj.close()
            for key in list(waiting.get_map().values()):  # still held: the view is stuck
                waiting.unregister(key.fileobj)
                key.fileobj.close()

    def _ended(self, connection: socket.socket, held_s: float) -> None:
        """Count how a connection the view ended `held_s` after it was made ended."""
        try:
            answer = connection.recv(len(BUSY_RESPONSE))
        except OSError:  # reset: refused before the request was read
            answer = b""
        if answer.startswith(b"HTTP/1.1 503") or held_s < DEFAULT_WEB.request_timeout_s / 2:
            self.refused += 1
        else:
            self.dropped += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(STOP_S)


class _NonReadingFoxgloveClients:
    """`count` WebSocket clients that subscribe to every channel and never read one byte
    after their handshake (a scout client, which reads, tells them the channels), kept up
    to `count` by reconnecting, until stopped."""

    def __init__(self, port: int, count: int) -> None:
        self.url, self.count = f"ws://127.0.0.1:{port}", count
        self.accepted = self.refused = self.closed = self.subscriptions = 0
        self.most_open = 0  # the most non-readers connected at once
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="non-readers", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        scout = until(lambda: self._scout(), "the Foxglove server", START_DEADLINE_S)
        clients: list[tuple[websocket.WebSocket, set[int]]] = []
        with scout:
            while not self._stop.is_set():
                while len(clients) < self.count and not self._stop.is_set():
                    try:
                        socket_ = websocket.create_connection(
                            self.url, subprotocols=[SUBPROTOCOL], timeout=2
                        )
                    except websocket.WebSocketBadStatusException:
                        self.refused += 1
                        break  # at the cap: try again later
                    except (OSError, websocket.WebSocketException):
                        break
                    self.accepted += 1
                    clients.append((socket_, set()))
                    self.most_open = max(self.most_open, len(clients))
                scout.pump(lambda c: False, 0.5)  # learn the channels advertised meanwhile
                for client in list(clients):
                    if not self._subscribe(client, set(scout.channels)):
                        clients.remove(client)
                        self.closed += 1
        for socket_, _ in clients:
            socket_.close()

    def _scout(self) -> FoxgloveClient | None:
        try:
            return FoxgloveClient(self.url, subscribe_all=False)
        except (OSError, websocket.WebSocketException):
            return None

    def _subscribe(self, client: tuple[websocket.WebSocket, set[int]], channels: set[int]) -> bool:
        """Subscribe `client` to the channels it has not subscribed to; False once closed."""
        socket_, subscribed = client
        new = sorted(channels - subscribed)
        if not new:
            return socket_.connected
        first_id = len(subscribed) + 1
        subscriptions = [{"id": first_id + k, "channelId": c} for k, c in enumerate(new)]
        try:
            socket_.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
        except (OSError, websocket.WebSocketException):
            return False
        subscribed.update(new)
        self.subscriptions += len(new)
        return True

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(STOP_S)


def _evaluate(out: Path, log: Path, *extra: str) -> subprocess.Popen:
    hub = f"tcp/127.0.0.1:{free_loopback_port()}"
    command = [sys.executable, "-m", "services.evaluate", *SOAK_CAMPAIGN, "--out", str(out),
               "--no-progress", "--listen", hub, *extra]  # fmt: skip
    with open(log, "wb") as sink:
        return subprocess.Popen(command, cwd=REPO_ROOT, stdout=sink, stderr=subprocess.STDOUT)


def _child_pid(log: Path, name: str) -> int | None:
    """The pid of `name`'s current process, from the supervisor's log."""
    found = [int(pid) for child, pid in _STARTED.findall(log.read_text()) if child == name]
    return found[-1] if found else None


def _campaign_wall_s(out: Path) -> float | None:
    """The wall time `services.evaluate` logged for its invocation into `out`."""
    try:
        return json.loads((out / "evaluations.jsonl").read_text().splitlines()[-1])["wall_time_s"]
    except (OSError, IndexError, ValueError, KeyError):
        return None


def _episodes(out: Path) -> dict[str, tuple]:
    """What an episode reproduces: metrics.json but its wall time, curves and trajectory."""
    episodes = {}
    for name, metrics in run_records(out).items():
        kept = {k: v for k, v in metrics.items() if k not in VOLATILE_METRICS}
        files = tuple((out / name / f).read_text() for f in ("curves.csv", "trajectory.csv"))
        episodes[name] = (kept, *files)
    return episodes


@pytest.mark.soak
def test_soak_a_campaign_beside_slow_http_and_non_reading_foxglove_clients_ends_as_alone(
    tmp_path,
):
    """SOAK, time-bounded (< 1 min): the campaign run alone and, at the same time, with
    `--web --foxglove` while 500 slow HTTP clients (a partial request each, held) and 50
    Foxglove clients that subscribe to every channel and never read press on the tools,
    in rounds, until it ends: both exit 0 with the same episodes (metrics, curves,
    trajectories); the soaked supervisor's RSS stays within 128 MiB of the lone one's; the
    web view holds at most `max_connections` connections (its threads bounded), refusing
    the rest with 503, and the Foxglove child's RSS stays bounded."""
    web_port, fox_port = free_loopback_port(), free_loopback_port()
    alone_log, soaked_log = tmp_path / "alone.log", tmp_path / "soaked.log"
    began = time.monotonic()
    alone = _evaluate(tmp_path / "alone", alone_log)
    soaked = _evaluate(tmp_path / "soaked", soaked_log, "--web", str(web_port), "--foxglove",
                       str(fox_port))  # fmt: skip
    peaks = _Peaks({
        "alone supervisor": lambda: alone.pid if alone.poll() is None else None,
        "soaked supervisor": lambda: soaked.pid if soaked.poll() is None else None,
        "web": lambda: _child_pid(soaked_log, "web"),
        "foxglove": lambda: _child_pid(soaked_log, "foxglove"),
    })  # fmt: skip
    http = foxglove = None
    try:
        until(lambda: _serves_http(web_port), "the web view", START_DEADLINE_S)
        http = _SlowHttpClients(web_port, SLOW_HTTP_CLIENTS)
        foxglove = _NonReadingFoxgloveClients(fox_port, NON_READING_FOXGLOVE_CLIENTS)
        codes = {"soaked": soaked.wait(RUN_DEADLINE_S)}  # the clients press until it ends
        for pressing in (http, foxglove):
            pressing.stop()
        codes["alone"] = alone.wait(RUN_DEADLINE_S)
    finally:
        for pressing in (http, foxglove):
            if pressing is not None:
                pressing.stop()
        peaks.stop()
        for process in (alone, soaked):
            if process.poll() is None:
                process.kill()
                process.wait()
        for name in ("web", "foxglove"):
            if (pid := _child_pid(soaked_log, name)) is not None and pid_alive(pid):
                kill_quietly(pid)
    wall_s = time.monotonic() - began
    figures = {
        "wall_s": round(wall_s, 1),
        "campaign_wall_s": {name: _campaign_wall_s(tmp_path / name) for name in CAMPAIGNS},
        "rss_mib": {name: round(rss / 2**20, 1) for name, rss in peaks.rss.items()},
        "threads": peaks.threads,
        "http": {"rounds": http.rounds, "refused": http.refused,
                 "held_then_dropped": http.dropped, "unconnected": http.unconnected},
        "foxglove": {"accepted": foxglove.accepted, "refused_503": foxglove.refused,
                     "most_open": foxglove.most_open, "closed_by_server": foxglove.closed,
                     "subscriptions": foxglove.subscriptions},
    }  # fmt: skip
    print("soak figures:", json.dumps(figures))
    (tmp_path / "figures.json").write_text(json.dumps(figures, indent=1))
    assert codes == {"soaked": 0, "alone": 0}, soaked_log.read_text()[-5000:]
    alone_episodes, soaked_episodes = _episodes(tmp_path / "alone"), _episodes(tmp_path / "soaked")
    assert len(alone_episodes) == 2 and soaked_episodes == alone_episodes
    # the pressure was there: the cap was reached and the non-readers subscribed
    assert http.refused > 0 and http.dropped > 0, figures
    assert foxglove.accepted > 0 and foxglove.subscriptions > 0 and foxglove.refused > 0, figures
    # and bounded
    rss = peaks.rss
    assert rss["soaked supervisor"] <= rss["alone supervisor"] + SUPERVISOR_EXTRA_RSS_BYTES, figures
    assert 0 < rss["foxglove"] <= FOXGLOVE_RSS_BYTES_AT_MOST, figures
    assert peaks.threads["web"] <= DEFAULT_WEB.max_connections + 32, figures
    assert foxglove.most_open < DEFAULT_FOXGLOVE.max_clients, figures  # the scout is one
    log = soaked_log.read_text()
    assert "restarted" not in log and "Traceback" not in log, log[-5000:]
