"""No input crashes a command (issue #53, defects 6-9): a forged map header, a starts file
that never ends, absurd team and pool sizes, bad `--set` values and negative seeds are
each one line on stderr and exit 2, before any process starts or any data is read."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from commands_at_once import run_python_m
from service_processes import free_loopback_port

from mapex.config import WorldConfig

FORGED_SHAPE = (200_000, 200_000)  # 40 GB of uint8 claimed by a 100-byte file
COMMAND_TIMEOUT_S = 120  # a command that reads /dev/zero or waits on a FIFO runs into this
MAX_STARTS = WorldConfig().max_starts


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, str]:
    """{name: path}: a map whose occupancy header is forged, and a FIFO starts file."""
    root = tmp_path_factory.mktemp("inputs")
    forged = root / "forged"
    forged.mkdir()
    with (forged / "occ_map.npy").open("wb") as handle:
        header = {"descr": "|u1", "fortran_order": False, "shape": FORGED_SHAPE}
        np.lib.format.write_array_header_1_0(handle, header)
        handle.write(bytes(16))
    np.save(forged / "valid_space.npy", np.ones((4, 4), np.uint8))
    os.mkfifo(root / "starts.fifo")
    many = root / "many-starts.json"  # one start more than world.max_starts, each a good one
    many.write_text(json.dumps({"generated:0": [[20, 30]] * (MAX_STARTS + 1)}))
    return {"forged": str(forged), "fifo": str(root / "starts.fifo"), "many": str(many),
            "out": str(root / "out")}  # fmt: skip


def _listen() -> list[str]:
    return ["--listen", f"tcp/127.0.0.1:{free_loopback_port()}"]


RUN = ["mapex", "run", "--steps", "5", "--no-progress"]
UP = ["services.up", "--steps", "5", "--no-progress"]
EVALUATE = ["services.evaluate", "--steps", "5", "--no-progress", "--no-report"]
WORLD = ["services.world", "--run", "bad"]
PLANNER = ["services.planner", "--run", "bad"]
AUDIT = ["mapex.audit", "--maps", "generated:0", "--no-progress"]
TRAIN = ["mapex.training.train"]

CASES = {
    # defect 6: a forged .npy header is refused from the header, before any data is read
    "run forged map": (RUN + ["--world", "{forged}"], "its map of shape (200000, 200000)"),
    "up forged map": (UP + ["--world", "{forged}"], "its map of shape (200000, 200000)"),
    "evaluate forged map": (EVALUATE + ["--maps", "{forged}"], "its map of shape (200000, 200000)"),
    "world forged map": (WORLD + ["--world", "{forged}"], "its map of shape (200000, 200000)"),
    # defect 7: a starts file that never ends, or never opens, is not read
    "evaluate /dev/zero starts": (
        EVALUATE + ["--maps", "generated:0", "--starts-file", "/dev/zero"],
        "/dev/zero is not a regular file (a character device)",
    ),
    "evaluate FIFO starts": (
        EVALUATE + ["--maps", "generated:0", "--starts-file", "{fifo}"],
        "starts.fifo is not a regular file (a FIFO)",
    ),
    # issue #64 item 7: more starts than world.max_starts, refused before any is judged (each
    # took 61 ms, so 200 k ran for hours in silence)
    "evaluate many starts in a file": (
        EVALUATE + ["--maps", "generated:0", "--starts-file", "{many}"],
        f"many-starts.json: more than world.max_starts ({MAX_STARTS}) starts",
    ),
    "evaluate many --starts": (
        EVALUATE + ["--maps", "generated:0", "--starts", ",".join(["0"] * (MAX_STARTS + 1))],
        f"--starts ({MAX_STARTS + 1}): more than world.max_starts ({MAX_STARTS}) starts",
    ),
    "audit many --starts": (
        AUDIT + ["--starts", str(MAX_STARTS + 1)],
        f"--starts ({MAX_STARTS + 1}): more than world.max_starts ({MAX_STARTS}) starts",
    ),
    # defect 8: team and pool sizes are capped by what the machine holds
    "run robots": (
        RUN + ["--method", "nearest_team", "--robots", "100000"],
        "team.max_robots (64)",
    ),
    "up robots": (UP + ["--method", "nearest_team", "--robots", "100000"], "team.max_robots (64)"),
    "evaluate robots": (
        EVALUATE + ["--maps", "generated:0", "--methods", "nearest_team", "--robots", "100000"],
        "team.max_robots (64)",
    ),
    "up runs": (UP + ["--runs", "100000"], "more than this machine holds"),
    "up replicas": (UP + ["--replicas", "100000"], "more than this machine holds"),
    "evaluate jobs": (
        EVALUATE + ["--maps", "generated:0", "--jobs", "100000"],
        "--jobs 100000 planners and 4 x --replicas 1 workers: 100004 processes, more than this "
        "machine holds",
    ),
    "audit jobs": (AUDIT + ["--jobs", "100000"], "more than this machine holds"),
    # defect 9: every value is checked when the configuration is built
    "run section": (RUN + ["--set", "sensor=1"], "override 'sensor=1': a section takes no value"),
    "run n_rays": (RUN + ["--set", "sensor.n_rays=0"], "sensor.n_rays must be in [1, 100000]"),
    "run cells_per_step": (
        RUN + ["--set", "motion.cells_per_step=0"],
        "motion.cells_per_step must be in [1, 65535]",
    ),
    "up section": (UP + ["--set", "sensor=1"], "a section takes no value"),
    "up timeout": (
        UP + ["--set", "services.step_timeout_s=-1"],
        "services.step_timeout_s must be > 0",
    ),
    "evaluate section": (EVALUATE + ["--maps", "generated:0", "--set", "sensor=1"], "a section"),
    "world section": (WORLD + ["--set", "sensor=1"], "a section takes no value"),
    "audit section": (AUDIT + ["--set", "sensor=1"], "a section takes no value"),
    "run seed": (RUN + ["--seed", "-1"], "seed -1 is out of range"),
    "up seed": (UP + ["--seed", "-1"], "seed -1 is out of range"),
    "evaluate seeds": (EVALUATE + ["--maps", "generated:0", "--seeds", "0,-1"], "seed -1 is out"),
    "planner seed": (PLANNER + ["--seed", "-1"], "seed -1 is out of range"),
    "audit seed": (AUDIT + ["--seed", "-1"], "seed -1 is out of range"),
    "train seed": (TRAIN + ["--set", "seed=-1"], "seed must be in [0, 4294967295], got -1"),
}


def command_case(args: list[str], inputs: dict[str, str]) -> list[str]:
    """`python -m` MODULE and its arguments (a case of run_python_m)."""
    module, *rest = [arg.format(**inputs) for arg in args]
    if module in ("services.up", "services.evaluate", "services.world"):
        rest += _listen()
    if module in ("services.up", "services.evaluate"):
        rest += ["--out", inputs["out"]]
    return [module, *rest]


def test_bad_input_is_one_line_and_exit_2_on_every_command(inputs):
    cases = [command_case(args, inputs) for args, _ in CASES.values()]
    results = dict(zip(CASES, run_python_m(cases, timeout_s=COMMAND_TIMEOUT_S), strict=True))
    wrong = []
    for name, (_, expected) in CASES.items():
        completed = results[name]
        lines = completed.stderr.strip().splitlines()
        if (
            completed.returncode != 2
            or "Traceback" in completed.stderr
            or not lines
            or expected not in lines[-1]
        ):
            wrong.append(f"{name}: exit {completed.returncode}, said {completed.stderr[-600:]!r}")
    assert not wrong, "\n".join(wrong)
    assert not os.path.exists(inputs["out"])  # nothing ran
