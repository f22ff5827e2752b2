"""services.supervisor with real child processes (tests/helpers/supervised_child.py)."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from pathlib import Path

import pytest
from service_processes import free_loopback_port, until
from up_processes import UpProcess

from services.keys import robot_key
from services.messages import PoseMessage
from services.supervisor import ProcessSpec, Supervisor, claim_hub, parse_tcp_endpoint
from services.zenoh_config import open_session, zenoh_config

HELPERS_DIR = Path(__file__).resolve().parents[1] / "helpers"
GRACE_S = 3.0  # the default grace; a loaded 2-core machine needs it for a polite child
STOP_MARGIN_S = 1.0  # stop() must be done within its grace period plus this
STEPS_BEFORE_STOP = 30  # by then the workers answer re-plans and whole-map predictions
EXIT_INTERRUPTED = 130  # services.up's exit after Ctrl-C


class Lines:
    """A log sink collecting lines (written from the forwarding threads)."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, line: str) -> None:
        with self.lock:
            self.lines.append(line)

    def has(self, line: str) -> bool:
        with self.lock:
            return line in self.lines

    def matching(self, start: str) -> list[str]:
        with self.lock:
            return [line for line in self.lines if line.startswith(start)]


def child(name: str, *args: str, restart: bool = False) -> ProcessSpec:
    """A supervised_child spec importable from the tests directory."""
    return ProcessSpec(
        name, "supervised_child", args, restart=restart, cwd=str(HELPERS_DIR), env={"X": "1"}
    )


@pytest.fixture
def supervised():
    """(supervisor, sink): the supervisor is stopped afterwards whatever happened."""
    sink = Lines()
    supervisor = Supervisor(sink, max_restarts=3)
    try:
        yield supervisor, sink
    finally:
        supervisor.stop(GRACE_S)


def pid_alive(pid: int) -> bool:
    """Whether `pid` is a live process (a zombie nobody reaped yet counts as dead)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
        return state not in ("Z", "X")
    except (FileNotFoundError, IndexError):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True


def test_lines_are_forwarded_with_the_name_prefix_as_they_come(supervised):
    supervisor, sink = supervised
    supervisor.start(child("echo", "--say", "hello", "--say", "wörld", "--raw", "ff41", "--sleep"))
    until(lambda: sink.has("[echo] ready"), "the ready line")
    assert supervisor.is_running("echo")  # forwarded while the child still runs
    echoed = sink.matching("[echo]")
    assert echoed == ["[echo] hello", "[echo] wörld", "[echo] \ufffdA", "[echo] ready"]
    assert sink.matching("[supervisor] started echo (pid ")


def test_a_killed_server_is_restarted_and_counted(supervised):
    supervisor, sink = supervised
    first = supervisor.start(child("worker", "--sleep", restart=True))
    until(lambda: sink.has("[worker] ready"), "the worker")
    assert supervisor.poll() == []
    os.kill(first.pid, signal.SIGKILL)
    assert until(supervisor.poll, "a restart") == ["worker"]
    assert supervisor.restarts == {"worker": 1}
    assert sink.has("[supervisor] worker exited with -9 (SIGKILL); restarted (1/3)")
    second = supervisor.process("worker")
    assert second.pid != first.pid and supervisor.is_running("worker")
    assert supervisor.poll() == []  # the exit is handled once


def test_a_finished_or_cleanly_ended_child_is_not_restarted(supervised):
    supervisor, sink = supervised
    supervisor.start(child("planner", "--exit", "3"))
    supervisor.start(child("server", "--exit", "0", restart=True))
    assert supervisor.wait("planner", 10.0) == 3
    assert supervisor.wait("server", 10.0) == 0
    assert supervisor.poll() == []
    assert supervisor.returncode("planner") == 3 and not supervisor.is_running("planner")
    assert supervisor.restarts == {}
    assert sink.has("[supervisor] planner exited with 3")
    assert sink.has("[supervisor] server exited with 0")


def test_max_restarts_is_respected(supervised):
    supervisor, sink = supervised
    supervisor.start(child("crasher", "--exit", "1", restart=True))
    gave_up = "[supervisor] crasher exited with 1; not restarted: gave up after 3 restarts"

    def given_up() -> bool:
        supervisor.poll()
        return sink.has(gave_up)

    until(given_up, "the supervisor to give up", deadline_s=20.0)
    assert supervisor.restarts == {"crasher": 3}
    assert len(sink.matching("[supervisor] crasher exited with 1; restarted")) == 3
    assert supervisor.poll() == [] and supervisor.restarts == {"crasher": 3}
    assert supervisor.returncode("crasher") == 1


def test_stop_leaves_no_process_even_when_one_ignores_sigterm(supervised):
    supervisor, sink = supervised
    supervisor.start(child("polite", "--sleep", restart=True))
    supervisor.start(child("stubborn", "--sleep", "--ignore-term", "--grandchild"))
    until(lambda: sink.has("[polite] ready") and sink.has("[stubborn] ready"), "both children")
    grandchild_pid = int(sink.matching("[stubborn] grandchild ")[0].split()[-1])
    processes = [supervisor.process("polite"), supervisor.process("stubborn")]
    try:
        started = time.monotonic()
        supervisor.stop(GRACE_S)
        assert time.monotonic() - started < GRACE_S + STOP_MARGIN_S
        assert all(process.poll() is not None for process in processes)
        until(lambda: not pid_alive(grandchild_pid), "the grandchild to die", deadline_s=2.0)
    finally:
        if pid_alive(grandchild_pid):
            os.kill(grandchild_pid, signal.SIGKILL)
    assert supervisor.returncode("polite") == 0
    assert supervisor.returncode("stubborn") == -signal.SIGKILL
    assert sink.has(
        f"[supervisor] killed stubborn: still running after the {GRACE_S:g} s grace period"
    )
    assert supervisor.poll() == []  # a stopped server is not restarted
    supervisor.stop(GRACE_S)  # idempotent


def test_stopping_up_while_its_workers_predict_kills_none_of_them(tmp_path):
    """Ctrl-C of `services.up` mid-run, eight workers busy on a shared 2-core machine: every
    child stops of SIGTERM within the grace period. A worker leaves a prediction still running
    after `predictor_drain_s` and skips the interpreter's teardown (seconds under load), which
    used to outlast the grace and end most workers in SIGKILL."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    up = UpProcess(
        tmp_path / "up.log", "--world", "generated:0", "--listen", endpoint, "--method", "mapex",
        "--steps", "2000", "--replicas", "2", "--run-prefix", "busy", "--out", str(tmp_path),
    )  # fmt: skip
    try:
        wait_for_step(endpoint, "busy-0", STEPS_BEFORE_STOP)  # re-plans and metrics predicted
        up.interrupt()
        assert up.wait(GRACE_S + 30) == EXIT_INTERRUPTED, up.log()
    finally:
        up.kill()
    log = up.log()
    workers = [name for name in up.children() if name.startswith("predictor-")]
    assert len(workers) == 8, log
    assert "SIGKILL" not in log and "still running after" not in log, log
    for name in workers:
        assert f"[supervisor] stopped {name} (0)" in log, log


def wait_for_step(endpoint: str, run: str, step: int) -> None:
    """Wait until robot r0 of `run` has published a pose of step `step` or later."""
    session = open_session(zenoh_config(connect=[endpoint], listen=[]))
    steps = []
    subscriber = session.declare_subscriber(
        robot_key(run, "r0", "pose"),
        lambda sample: steps.append(PoseMessage.decode(sample.payload.to_bytes()).t),
    )
    try:
        until(lambda: steps and steps[-1] >= step, f"the run to reach step {step}", 300)
    finally:
        subscriber.undeclare()
        session.close()


def test_the_context_manager_stops_its_children():
    with Supervisor(Lines()) as supervisor:
        process = supervisor.start(child("sleeper", "--sleep"))
    assert process.poll() is not None


def test_a_name_runs_once_at_a_time(supervised):
    supervisor, _ = supervised
    supervisor.start(child("twin", "--sleep"))
    with pytest.raises(ValueError, match="already running"):
        supervisor.start(child("twin", "--sleep"))


def test_claim_hub_tells_a_free_port_from_a_listening_one():
    port = free_loopback_port()
    assert claim_hub(f"tcp/127.0.0.1:{port}")
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", port))
        listener.listen()
        assert not claim_hub(f"tcp/127.0.0.1:{port}")
    assert claim_hub(f"tcp/127.0.0.1:{port}")


def test_claim_hub_treats_a_port_left_in_time_wait_as_free():
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        with socket.create_connection(("127.0.0.1", port)) as client:
            accepted, _ = listener.accept()
            accepted.close()  # the hub side closes first: its end stays in TIME_WAIT
            client.recv(1)
    assert claim_hub(f"tcp/127.0.0.1:{port}")


@pytest.mark.parametrize(
    "endpoint", ["udp/127.0.0.1:7447", "127.0.0.1:7447", "tcp/127.0.0.1", "tcp/:7447"]
)
def test_claim_hub_rejects_other_endpoints(endpoint):
    with pytest.raises(ValueError, match="hub endpoint"):
        claim_hub(endpoint)


def test_parse_tcp_endpoint():
    assert parse_tcp_endpoint("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert parse_tcp_endpoint("tcp/[::1]:7447#iface=lo") == ("::1", 7447)
