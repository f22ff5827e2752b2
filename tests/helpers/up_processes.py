"""Helpers for tests that run `python -m services.up` (and friends) as real processes."""

from __future__ import annotations

import csv
import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
from service_processes import REPO_ROOT, STOP_DEADLINE_S

RUN_DEADLINE_S = 600.0  # a whole supervised run on a shared 2-core machine
_STARTED = re.compile(r"\[supervisor\] started (\S+) \(pid (\d+)\)")


class UpProcess:
    """One `services.up` child process logging to a file; `kill` leaves nothing behind."""

    def __init__(self, log_path: Path, *args: str) -> None:
        self.log_path = log_path
        command = [sys.executable, "-m", "services.up", "--no-progress", *args]
        with open(log_path, "wb") as log:
            self.process = subprocess.Popen(command, cwd=REPO_ROOT, stdout=log, stderr=log)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def children(self) -> dict[str, list[int]]:
        """Every child process up started so far, by name (restarts add pids)."""
        found: dict[str, list[int]] = {}
        for name, pid in _STARTED.findall(self.log()):
            found.setdefault(name, []).append(int(pid))
        return found

    def wait(self, timeout_s: float = RUN_DEADLINE_S) -> int:
        return self.process.wait(timeout_s)

    def interrupt(self) -> None:
        self.process.send_signal(signal.SIGINT)

    def kill(self) -> None:
        """Kill up and every child it started (a test failing midway leaves nothing)."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(STOP_DEADLINE_S)
        for pids in self.children().values():
            for pid in pids:
                kill_quietly(pid)


def kill_quietly(pid: int) -> None:
    try:
        import os

        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def pid_alive(pid: int) -> bool:
    """Whether `pid` is a live process (a zombie child of someone else counts as gone)."""
    try:
        status = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return status.rsplit(")", 1)[1].split()[0] != "Z"


def read_run(folder: Path) -> tuple[dict, np.ndarray, list[list[str]]]:
    """(metrics.json, trajectory int (n, 2), curves.csv rows) of a results folder."""
    metrics = json.loads((folder / "metrics.json").read_text())
    trajectory = np.loadtxt(folder / "trajectory.csv", delimiter=",", skiprows=1, dtype=np.int64)
    with (folder / "curves.csv").open() as handle:
        curves = list(csv.reader(handle))
    return metrics, trajectory[:, 1:], curves
