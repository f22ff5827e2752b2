"""The `python -m mapex` command line: a real small run and one-line errors on bad input."""

import json
import subprocess
import sys

import pytest
from commands_at_once import run_python_m

from mapex.cli import main


def run_cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mapex", *args], capture_output=True, text=True, cwd=cwd, timeout=300
    )


def test_run_writes_the_results_folder(tmp_path):
    out = tmp_path / "run"
    code = main(
        [
            "run",
            "--world",
            "generated:2",
            "--method",
            "mapex",
            "--steps",
            "60",
            "--no-progress",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "mapex" and metrics["steps"] == 60
    assert 0.0 < metrics["auc"]["coverage"] <= 1.0
    assert (out / "curves.csv").read_text().splitlines()[0] == "step,coverage,iou,tu"
    assert len((out / "trajectory.csv").read_text().splitlines()) >= 2
    assert (out / "final.png").read_bytes()[:4] == b"\x89PNG"


def test_an_oracle_run_says_so_and_records_its_predictor(tmp_path, capsys):
    out = tmp_path / "oracle"
    code = main(["run", "--world", "generated:2", "--method", "mapex", "--predictor", "oracle",
                 "--steps", "60", "--no-progress", "--out", str(out)])  # fmt: skip
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["predictor"] == "oracle" and metrics["degraded_steps"] == []
    assert metrics["auc"]["iou"] > 0.99  # G's map is the truth
    assert "ground truth is the prediction" in capsys.readouterr().err


def test_a_team_run_writes_every_robots_trajectory_and_the_team_record(tmp_path):
    code = main(["run", "--world", "generated:2", "--method", "nearest_team", "--robots", "3",
                 "--steps", "40", "--no-progress", "--out", str(tmp_path / "team")])  # fmt: skip
    assert code == 0
    metrics = json.loads((tmp_path / "team" / "metrics.json").read_text())
    team = metrics["team"]
    assert metrics["method"] == "nearest_team" and team["robots"] == 3
    assert len(team["path_length_m"]) == len(team["starts"]) == 3 and 0 <= team["overlap"] <= 1
    rows = (tmp_path / "team" / "trajectories.csv").read_text().splitlines()
    assert rows[0] == "step,robot,row,col" and len(rows) == 1 + 3 * 41
    assert (tmp_path / "team" / "final.png").read_bytes()[:4] == b"\x89PNG"


def test_a_method_that_does_not_coordinate_runs_as_a_team_sharing_one_map(tmp_path):
    code = main(["run", "--world", "generated:2", "--method", "nearest", "--robots", "2",
                 "--steps", "40", "--no-progress", "--out", str(tmp_path / "pair")])  # fmt: skip
    assert code == 0
    metrics = json.loads((tmp_path / "pair" / "metrics.json").read_text())
    assert metrics["method"] == "nearest" and metrics["team"]["robots"] == 2


BAD_INPUT = [
    (["--world", "/no/such/map"], "/no/such/map"),
    (["--world", "generated:abc"], "abc"),
    (["--method", "best"], "invalid choice"),
    (["--steps", "0"], "--steps"),
    (["--steps", "au"], "--steps must be a whole number or 'auto'"),
    (["--until-iou", "1.5"], "--until-iou must be in (0, 1]"),
    (["--set", "until_iou=-1"], "until_iou must be in (0, 1]"),
    (["--set", "visibility.nosuch=1"], "nosuch"),
    (["--start", "7"], "corners are 0-3"),
    (["--start", "1,x"], "expected a corner 0-3 or a cell ROW,COL"),
    (["--start", "0,0"], "world 'generated:0': start cell (0, 0) is on a wall"),
    (["--start", "9000,40"], "start cell (9000, 40) is outside the map"),
    (["--precision", "float16"], "invalid choice"),
    (["--predictor", "classical", "--precision", "bfloat16"], "only the 'lama' predictor"),
    (["--predictor", "oracle", "--views", "1"], "only the 'lama' predictors"),
    (["--set", "world.max_cells=1000"], "above the limit of 1,000"),
    (["--robots", "0", "--method", "mapex_team"], "--robots must be at least 1"),
    (["--robots", "0"], "--robots must be at least 1"),
    (["--robots", "x"], "invalid int value"),
    (["--robots", "100000", "--method", "nearest_team"], "more than team.max_robots (64)"),
    (["--set", "sensor=1"], "override 'sensor=1': a section takes no value"),
    (["--set", "sensor.n_rays=0"], "sensor.n_rays must be in [1, 100000], got 0"),
    (["--set", "motion.cells_per_step=0"], "motion.cells_per_step must be in [1, 65535]"),
    (["--seed", "-1"], "seed -1 is out of range"),
    (
        ["--robots", "3", "--method", "nearest_team", "--set", "team.spacing_cells=5000"],
        "room for 1 robots 5000 cells apart",
    ),
]


@pytest.fixture(scope="module")
def bad_input_runs() -> dict[tuple[str, ...], subprocess.CompletedProcess]:
    """`python -m mapex run` with each of BAD_INPUT, all run at once (each only parses and
    fails)."""
    cases = [["mapex", "run", "--no-progress", *args] for args, _ in BAD_INPUT]
    return dict(zip((tuple(args) for args, _ in BAD_INPUT), run_python_m(cases), strict=True))


@pytest.mark.slow  # runs the command in a process of its own
@pytest.mark.parametrize("args, message", BAD_INPUT)
def test_bad_input_gives_one_line_error(args, message, bad_input_runs):
    done = bad_input_runs[tuple(args)]
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    error_lines = [line for line in done.stderr.splitlines() if "error" in line]
    assert len(error_lines) == 1 and message in error_lines[0]


@pytest.mark.slow  # runs the command in a process of its own
def test_a_recording_that_exists_is_refused_and_kept(tmp_path):
    (tmp_path / "run.mcap").write_bytes(b"an older recording")
    done = run_cli("run", "--no-progress", "--record", str(tmp_path / "run.mcap"))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    error_lines = [line for line in done.stderr.splitlines() if "error" in line]
    assert len(error_lines) == 1 and "exists" in error_lines[0]
    assert (tmp_path / "run.mcap").read_bytes() == b"an older recording"


@pytest.mark.slow  # runs the command in a process of its own
def test_bad_map_file_gives_one_line_error(tmp_path):
    (tmp_path / "occ_map.npy").write_bytes(b"not a numpy file")
    done = run_cli("run", "--no-progress", "--world", str(tmp_path))
    assert done.returncode == 2
    assert "Traceback" not in done.stderr and "occ_map.npy" in done.stderr


@pytest.mark.slow  # runs the command in a process of its own
def test_a_bad_out_is_refused_before_the_run(tmp_path):
    (tmp_path / "taken").write_text("a file")
    done = run_cli("run", "--no-progress", "--out", str(tmp_path / "taken" / "run"))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "cannot write results to" in done.stderr.strip().splitlines()[-1]
    assert "coverage AUC" not in done.stdout  # nothing was run
