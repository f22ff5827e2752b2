"""A service stopped while it still sets up ends at once (issue #53, defect 8).

An orphaned world that was setting up a huge team once ignored SIGTERM for minutes: its
graceful handler only set an event that nobody looked at before serving. Each service's
`__main__` now makes SIGINT/SIGTERM end the process at once until it serves
(`services.serving.exit_on_signals`).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from service_processes import REPO_ROOT, free_loopback_port, until

SIDE_CELLS = 10_000  # a 0.05 m map of 10000 x 10000: seconds of loading and setting up
PROMPT_EXIT_S = 1.5  # a stopped process is gone this soon (setting up takes several times more)


def big_map(directory: Path) -> Path:
    """A KTH map directory whose world (5000 x 5000 cells) takes seconds to set up."""
    directory.mkdir()
    occupancy = np.full((SIDE_CELLS, SIDE_CELLS), 254, dtype=np.uint8)
    occupancy[::400], occupancy[:, ::600], occupancy[-1], occupancy[:, -1] = 0, 0, 0, 0
    np.save(directory / "occ_map.npy", occupancy)
    np.save(directory / "valid_space.npy", np.ones_like(occupancy))
    return directory


def catches_sigterm(pid: int) -> bool:
    """Whether process `pid` has installed a SIGTERM handler (SigCgt in /proc)."""
    status = Path(f"/proc/{pid}/status").read_text()
    caught = next(line for line in status.splitlines() if line.startswith("SigCgt:"))
    return bool(int(caught.split()[1], 16) & (1 << (signal.SIGTERM - 1)))


def test_a_world_stopped_while_loading_a_big_map_exits_at_once(tmp_path):
    world_dir = big_map(tmp_path / "big")
    world = subprocess.Popen(
        [sys.executable, "-m", "services.world", "--run", "sigterm", "--world", str(world_dir),
         "--set", "world.max_cells=40000000", "--listen", f"tcp/127.0.0.1:{free_loopback_port()}"],
        cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        until(lambda: catches_sigterm(world.pid), "the world's SIGTERM handler", deadline_s=60)
        world.send_signal(signal.SIGTERM)  # it now loads the map, then sets up, then serves
        sent = time.monotonic()
        code = world.wait(timeout=60)
        waited = time.monotonic() - sent
        said = world.stderr.read()
    finally:
        world.kill()
        world.wait()
    assert "serving world" not in said  # it never got as far as serving
    assert code == 128 + signal.SIGTERM, said
    assert waited < PROMPT_EXIT_S, f"exited {waited:.1f} s after SIGTERM"


def test_a_worker_stopped_while_it_loads_its_weights_exits_at_once():
    """SIGTERM once the worker's handler is in, before it serves: it exits at once with
    128 + SIGTERM rather than load its weights first and exit 0 after (seconds on a loaded
    machine: services.up's grace period ran out on such workers, issue #54)."""
    for _attempt in range(3):  # again only when the worker served before the signal came
        code, said = stop_a_starting_worker()
        if "serving member" not in said:
            break
    assert "serving member" not in said, said  # it never got as far as serving
    assert code == 128 + signal.SIGTERM, said


def stop_a_starting_worker() -> tuple[int, str]:
    """SIGTERM a predictor worker as soon as it catches SIGTERM: its exit code and log."""
    worker = subprocess.Popen(
        [sys.executable, "-m", "services.predictor", "--member", "g",
         "--listen", f"tcp/127.0.0.1:{free_loopback_port()}"],
        cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        until(lambda: catches_sigterm(worker.pid), "the worker's SIGTERM handler", 120)
        worker.send_signal(signal.SIGTERM)
        code = worker.wait(timeout=60)
        return code, worker.stderr.read()
    finally:
        worker.kill()
        worker.wait()
