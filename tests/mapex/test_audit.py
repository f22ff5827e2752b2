"""The stall audit: start cells, the reachable set, the flag rule and the command."""

import subprocess
import sys

import numpy as np
import pytest
from handmade_worlds import ROOM_CENTRE, slit_room_world
from service_processes import REPO_ROOT

from mapex.audit import AuditRow, flag, reachable_valid_cells, spread_starts
from mapex.config import ExplorationConfig
from mapex.worlds import load_world
from mapex.worlds.starts import eligible_start_cells


def test_starts_are_eligible_distinct_spread_and_seeded():
    world = load_world("generated:0")
    starts = spread_starts(world, 10, 3, seed=4)
    eligible = eligible_start_cells(world, 3)
    assert len(set(starts)) == 10 and all(eligible[r, c] for r, c in starts)
    assert spread_starts(world, 10, 3, seed=4) == starts
    assert spread_starts(world, 10, 3, seed=5) != starts
    cells = np.array(starts)
    gaps = np.hypot(*(cells[:, None] - cells[None]).transpose(2, 0, 1))
    assert gaps[~np.eye(10, dtype=bool)].min() > 20  # spread, not clumped


def test_the_reachable_set_stops_at_a_slit_the_robot_cannot_pass():
    world = slit_room_world()
    reachable = reachable_valid_cells(world, ROOM_CENTRE, ExplorationConfig())
    assert reachable[ROOM_CENTRE] and reachable[61:99, 11:49].all()  # the room, off its walls
    assert not reachable[:56].any()  # nothing beyond the slit


@pytest.mark.parametrize(
    ("end", "unknown", "flagged"),
    [("budget", 0.5, False), ("explored", 0.01, False), ("unreachable", 0.03, True),
     ("explored", 0.021, True)],
)  # fmt: skip
def test_only_early_ends_with_reachable_space_unknown_are_flagged(end, unknown, flagged):
    row = AuditRow("w", (1, 2), "nearest", end, None, 0.5, unknown, False)
    assert flag(row, 0.02).flagged is flagged


def audit(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mapex.audit", "--no-progress", *args],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip


@pytest.mark.slow  # runs the command in a process of its own
def test_the_command_prints_every_run_and_a_summary(tmp_path):
    done = audit("--maps", "generated:0", "--starts", "2", "--steps", "40", "--jobs", "1",
                 "--out", str(tmp_path / "rows.json"))  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.count("| generated:0 | ") == 2 * 2 + 2  # runs, then the summary
    assert "4 runs, 0 flagged" in done.stdout
    assert (tmp_path / "rows.json").read_text().count('"end_reason"') == 4


@pytest.mark.slow  # runs the command in a process of its own
@pytest.mark.parametrize(
    ("args", "message"),
    [(["--maps", "generated:0", "--methods", "best"], "unknown method best"),
     (["--maps", "/no/such/map"], "no such map directory"),
     (["--maps", "generated:0", "--starts", "0"], "--starts must be at least 1"),
     (["--maps", "generated:0", "--out", "/no/such/dir/rows.json"], "no folder /no/such/dir")],
)  # fmt: skip
def test_bad_input_fails_in_one_line(args, message):
    done = audit(*args)
    assert done.returncode == 2
    assert message in done.stderr.strip().splitlines()[-1] and "Traceback" not in done.stderr
