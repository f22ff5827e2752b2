"""Helpers for tests that start real service processes on loopback (no fork, none left behind)."""

from __future__ import annotations

import contextlib
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
STOP_DEADLINE_S = 5.0  # SIGINT to exit (DESIGN.md)
ROUTER_START_DEADLINE_S = 60.0  # a cold interpreter on a loaded machine; the start takes seconds
ROUTER_READY = re.compile(r"router ([0-9a-f]+) listening on")


def free_loopback_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@contextlib.contextmanager
def taken_loopback_port() -> Iterator[int]:
    """A loopback port something listens on while the block runs (a port that is taken)."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        yield taken.getsockname()[1]


def read_until_closed(connection: socket.socket) -> bytes:
    """Everything the peer sends until it closes the connection (a reset ends it too)."""
    received = b""
    try:
        while chunk := connection.recv(65536):
            received += chunk
    except ConnectionResetError:
        pass
    return received


def until(condition, what: str, deadline_s: float = 5.0):
    """Poll `condition` until truthy; fail naming `what` after `deadline_s`."""
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.02)
    pytest.fail(f"timed out waiting for {what}")


class ServiceProcesses:
    """`python -m <module>` processes connected to one hub, each logging to a file;
    `kill_all` leaves none behind."""

    def __init__(self, hub_endpoint: str, log_dir: Path) -> None:
        self.hub_endpoint = hub_endpoint
        self.log_dir = log_dir
        self.processes: dict[str, subprocess.Popen] = {}

    def spawn(self, name: str, module: str, *args: str) -> subprocess.Popen:
        command = [sys.executable, "-m", module, *args, "--connect", self.hub_endpoint]
        with open(self.log_path(name), "wb") as log:
            process = subprocess.Popen(command, cwd=REPO_ROOT, stdout=log, stderr=log)
        self.processes[name] = process
        return process

    def log_path(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def log_of(self, name: str) -> str:
        return self.log_path(name).read_text(errors="replace")

    def wait_until_announced(self, name: str, announced, deadline_s: float) -> None:
        """Wait for `announced()`; fail with the log if the process exits first."""

        def alive() -> bool:
            if self.processes[name].poll() is not None:
                pytest.fail(f"{name} exited early:\n{self.log_of(name)}")
            return announced()

        until(alive, f"{name} to announce itself", deadline_s)

    def kill_all(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                process.kill()
            process.wait(STOP_DEADLINE_S)


@dataclass
class RouterProcess:
    """A `python -m deploy.router` process and where it logs."""

    process: subprocess.Popen
    log_path: Path
    endpoint: str
    zid: str = ""

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def spawn_router(log_dir: Path, endpoint: str) -> RouterProcess:
    """Start `python -m deploy.router --listen endpoint` (call `wait_router_ready` next)."""
    log_path = log_dir / f"router-{endpoint.rsplit(':', 1)[1]}.log"
    command = [sys.executable, "-m", "deploy.router", "--listen", endpoint]
    with open(log_path, "wb") as log:
        process = subprocess.Popen(command, cwd=REPO_ROOT, stdout=log, stderr=log)
    return RouterProcess(process, log_path, endpoint)


def wait_router_ready(router: RouterProcess) -> None:
    """Wait for the 'listening' line (the signal handlers are installed before it), so that
    clients started next can connect."""

    def listening():
        if router.process.poll() is not None:
            pytest.fail(f"the router exited early:\n{router.log()}")
        return ROUTER_READY.search(router.log())

    router.zid = until(listening, "the router to listen", ROUTER_START_DEADLINE_S).group(1)


def kill_router(router: RouterProcess) -> None:
    if router.process.poll() is None:
        router.process.kill()
    router.process.wait(STOP_DEADLINE_S)
