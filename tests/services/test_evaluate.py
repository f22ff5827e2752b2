"""Batch evaluation: episode planning, atomic resumable results, a killed-and-resumed run."""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from commands_at_once import run_python_m
from service_processes import REPO_ROOT, free_loopback_port, until
from shard_runs import comparable_tables, pool_warnings, run_records
from up_processes import pid_alive

import mapex.worlds.starts as starts_module
from mapex.budget import auto_steps
from mapex.config import ConfigError, ExplorationConfig, WorldConfig
from mapex.episode import run_episode
from mapex.results import write_results
from mapex.worlds import load_world
from mapex.worlds.starts import eligible_start_cells
from services.config import RunConfig, ServicesConfig
from services.evaluate import (
    BROKEN_DIR,
    Episode,
    build_parser,
    finished,
    plan_episodes,
    planner_folder,
    planner_spec,
    publish,
    read_starts_file,
    remove_staging,
    run_episodes,
)
from services.pool import resolve_pool_predictor, worker_specs

SMALL = ["--maps", "generated:0", "--methods", "nearest,mapex", "--starts", "0,1",
         "--steps", "60"]  # fmt: skip


def evaluate(out, *extra: str, log=None) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "services.evaluate", *SMALL, "--out", str(out), "--no-progress",
        "--listen", f"tcp/127.0.0.1:{free_loopback_port()}", *extra,
    ]  # fmt: skip
    return subprocess.Popen(
        command, cwd=REPO_ROOT, stdout=log or subprocess.DEVNULL, stderr=log or subprocess.STDOUT
    )


def test_episodes_cover_every_combination_with_run_folder_names():
    episodes = plan_episodes(["generated:0"], ["nearest", "mapex"], [0, 3], [0, 1])
    assert len(episodes) == 8 and len({e.name for e in episodes}) == 8
    assert episodes[0].name == "generated_0-nearest-start0-seed0"
    assert (
        Episode("x", "50037764_PLAN1", "mapex", 2, 0).run_id == "50037764_plan1-mapex-start2-seed0"
    )


def test_auto_steps_are_resolved_per_world_and_until_iou_reaches_the_planner(tmp_path):
    worlds = ["generated:0", "generated:3"]
    episodes = plan_episodes(worlds, ["nearest"], [0], [0], steps=None)
    assert [e.steps for e in episodes] == [auto_steps(load_world(w)) for w in worlds]
    assert plan_episodes(worlds, ["nearest"], [0], [0], steps=70)[0].steps == 70
    args = build_parser().parse_args(
        [*SMALL, "--until-iou", "0.95", "--steps", "auto", "--set", "motion.cells_per_step=2"]
    )
    run_config = RunConfig(ExplorationConfig(until_iou=args.until_iou))  # as main builds it
    settings = run_config.with_overrides(args.overrides).as_overrides()
    spec = planner_spec(episodes[1], settings, tmp_path, ["--connect", "tcp/127.0.0.1:1"])
    assert spec.args[spec.args.index("--steps") + 1] == str(episodes[1].steps)
    assert spec.args[-6:] == (
        "--set", "until_iou=0.95", "--set", "motion.cells_per_step=2",
        "--connect", "tcp/127.0.0.1:1",
    )  # fmt: skip


def test_a_folder_without_the_time_to_level_record_is_run_again(tmp_path, sound_run, caplog):
    shutil.copytree(sound_run, tmp_path / EPISODE.name)
    metrics = json.loads((tmp_path / EPISODE.name / "metrics.json").read_text())
    del metrics["reached"]
    (tmp_path / EPISODE.name / "metrics.json").write_text(json.dumps(metrics))
    with caplog.at_level("WARNING"):
        assert not finished(EPISODE, tmp_path, plain(SHORT))
    assert "no time-to-level record" in caplog.text


def test_team_methods_run_as_teams_of_the_asked_size():
    episodes = plan_episodes(["generated:0"], ["mapex", "mapex_team"], [1], [0], robots=2)
    assert [(e.method, e.robots) for e in episodes] == [("mapex", 1), ("mapex_team", 2)]
    assert episodes[1].name == "generated_0-mapex_team-start1-seed0-team2"


def test_an_evaluation_runs_a_team_through_the_pool(tmp_path):
    out = tmp_path / "out"
    command = [
        sys.executable, "-m", "services.evaluate", "--maps", "generated:0", "--methods",
        "nearest_team", "--robots", "2", "--steps", "30", "--starts", "0", "--out", str(out),
        "--no-progress", "--listen", f"tcp/127.0.0.1:{free_loopback_port()}",
        "--set", "services.predict_timeout_s=20",
    ]  # fmt: skip
    completed = subprocess.run(command, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert completed.returncode == 0, completed.stderr
    (record,) = run_records(out).values()
    assert record["method"] == "nearest_team" and record["team"]["robots"] == 2
    assert len(record["team"]["path_length_m"]) == 2
    said = settings_lines(completed.stderr)  # every child runs with the evaluation's --set
    assert {"episode", "predictor-g", "predictor-g1", "predictor-g2", "predictor-g3"} <= set(said)
    assert all("services.predict_timeout_s=20.0" in line for line in said.values()), said


def settings_lines(log: str) -> dict[str, str]:
    """Each child's settings line (`[<name>] ... settings: ...`), by name without its run."""
    found = re.findall(r"\[([a-z0-9_-]+)\][^\n]* INFO (settings: [^\n]*)", log)
    return {re.sub(r"^episode-.*", "episode", name): line for name, line in found}


def test_an_oracle_pool_is_one_worker_and_its_runs_are_named_apart():
    """Episodes under the oracle are `<method>@oracle` (one that reads no prediction too: its
    IoU and TU are the oracle's); their planners ask for the oracle, whose pool is one worker
    of member g with no network flags."""
    episodes = plan_episodes(["generated:0"], ["nearest", "mapex"], [0], [0], predictor="oracle")
    assert [e.name for e in episodes] == [
        "generated_0-nearest@oracle-start0-seed0",  # the same run, but the oracle's IoU / TU
        "generated_0-mapex@oracle-start0-seed0",
    ]
    assert episodes[1].run_id == "generated_0-mapex_oracle-start0-seed0"
    spec = planner_spec(episodes[1], [], Path("out"), [])
    assert spec.args[spec.args.index("--predictor") + 1] == "oracle"
    args = build_parser().parse_args([*SMALL, "--predictor", "oracle"])
    resolve_pool_predictor(args)
    (worker,) = worker_specs(args.members, 1, 1, [], predictor="oracle")
    assert worker.member == "g" and "--threads" not in worker.args
    assert worker.args[worker.args.index("--predictor") + 1] == "oracle"
    default = plan_episodes(["generated:0"], ["mapex"], [0], [0])[0]
    assert "--predictor" not in planner_spec(default, [], Path("out"), []).args


def test_an_oracle_evaluation_serves_each_planner_s_world_to_its_worker(tmp_path):
    """The planners simulate their worlds and serve their ground truths; the one oracle
    worker answers every re-plan from them, and the report labels the run mapex@oracle."""
    out = tmp_path / "out"
    command = [
        sys.executable, "-m", "services.evaluate", "--maps", "generated:0", "--methods",
        "mapex,nearest", "--steps", "40", "--starts", "0", "--predictor", "oracle",
        "--out", str(out), "--no-progress", "--listen", f"tcp/127.0.0.1:{free_loopback_port()}",
    ]  # fmt: skip
    completed = subprocess.run(command, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert completed.returncode == 0, completed.stderr
    records = run_records(out)
    assert set(records) == {
        "generated_0-mapex@oracle-start0-seed0",
        "generated_0-nearest@oracle-start0-seed0",
    }
    oracle = records["generated_0-mapex@oracle-start0-seed0"]
    assert oracle["predictor"] == "oracle" and oracle["degraded_steps"] == []
    assert oracle["replans"] > 1 and oracle["auc"]["iou"] > 0.99
    assert re.findall(r"started (predictor-\S+)", completed.stderr) == ["predictor-g"]
    assert "| mapex@oracle |" in (out / "report" / "report.md").read_text()
    assert "the ground truth is the prediction" in completed.stderr


def test_a_starts_file_gives_each_map_its_own_cells(tmp_path):
    path = tmp_path / "starts.json"
    path.write_text(json.dumps({"generated:0": [[20, 30], [25, 40]], "other": [[1, 1]]}))
    episodes = plan_episodes(["generated:0"], ["nearest"], read_starts_file(path), [0])
    assert [e.start for e in episodes] == [(20, 30), (25, 40)]
    assert episodes[0].name == "generated_0-nearest-start-r20c30-seed0"


def test_an_evaluation_runs_the_cells_of_a_starts_file(tmp_path):
    (tmp_path / "starts.json").write_text(json.dumps({"generated:0": [[20, 30]]}))
    out = tmp_path / "out"
    command = [
        sys.executable, "-m", "services.evaluate", "--maps", "generated:0", "--methods",
        "nearest", "--steps", "30", "--starts-file", str(tmp_path / "starts.json"),
        "--out", str(out), "--no-progress", "--listen", f"tcp/127.0.0.1:{free_loopback_port()}",
    ]  # fmt: skip
    completed = subprocess.run(command, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert completed.returncode == 0, completed.stderr
    records = run_records(out)
    assert list(records) == ["generated_0-nearest-start-r20c30-seed0"]
    record = records["generated_0-nearest-start-r20c30-seed0"]
    assert record["start"] == [20, 30] and record["start_index"] is None
    assert record["end_reason"] in ("budget", "explored", "unreachable")


@pytest.mark.parametrize(
    ("text", "message"),
    [("[]", "a JSON object"), ("{", "Expecting"), ('{"m": []}', "non-empty list"),
     ('{"m": [[1, -2]]}', "[row, col]"), ('{"m": [[1, true]]}', "[row, col]")],
)  # fmt: skip
def test_a_malformed_starts_file_is_refused(tmp_path, text, message):
    (tmp_path / "s.json").write_text(text)
    with pytest.raises(ValueError, match=re.escape(message)):
        read_starts_file(tmp_path / "s.json")


def test_the_starts_of_a_file_are_judged_at_once(tmp_path, monkeypatch):
    """A map's starts cost the map computations of one start, however many there are (issue
    #64, item 7: they were two per start, 61 ms, so 200 k starts ran > 300 s silently)."""
    world = load_world("generated:0")
    cells = np.argwhere(eligible_start_cells(world, 3))[::97][:300].tolist()
    calls = []
    real = starts_module.main_free_space
    monkeypatch.setattr(starts_module, "main_free_space", lambda w: calls.append(1) or real(w))
    counts = []
    for starts in (cells[:1], cells):
        path = tmp_path / "starts.json"
        path.write_text(json.dumps({"generated:0": starts}))
        calls.clear()
        episodes = plan_episodes(["generated:0"], ["nearest"], read_starts_file(path), [0])
        assert [list(e.start) for e in episodes] == starts
        counts.append(len(calls))
    assert counts[1] == counts[0] <= 2


def test_more_starts_than_the_cap_are_refused_before_the_file_is_parsed_past_them(tmp_path):
    path = tmp_path / "starts.json"
    capped = WorldConfig(max_starts=3)
    path.write_text('{"a": [[1, 2], [3, 4]], "b": [[5, 6]]}')
    assert read_starts_file(path, world=capped) == {"a": [(1, 2), (3, 4)], "b": [(5, 6)]}
    path.write_text('{"a": [[1, 2], [3, 4]], "b": [[5, 6], [7, 8]], "c": ')  # unfinished
    with pytest.raises(ConfigError) as refused:
        read_starts_file(path, world=capped)
    assert str(refused.value) == (
        f"starts file {path}: more than world.max_starts (3) starts; "
        "--set world.max_starts=N raises the cap"
    )


SHORT = ExplorationConfig(steps=20)
EPISODE = Episode("generated:0", "generated:0", "nearest", 0, 0)


def plain(config: ExplorationConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(config)))


@pytest.fixture(scope="module")
def sound_run(tmp_path_factory):
    """A real finished folder of EPISODE (20 steps), to copy and damage."""
    result = run_episode(load_world("generated:0"), "nearest", None, 0, 0, SHORT)
    return write_results(result, load_world("generated:0"), tmp_path_factory.mktemp("r") / "run")


def test_only_complete_folders_count_and_staging_is_removed(tmp_path, sound_run):
    assert not finished(EPISODE, tmp_path)
    (tmp_path / f".{EPISODE.name}.abc").mkdir()
    shutil.copytree(sound_run, tmp_path / EPISODE.name)
    assert finished(EPISODE, tmp_path, plain(SHORT))
    assert remove_staging(tmp_path) == 1 and remove_staging(tmp_path) == 0


def test_a_shard_removes_the_half_written_folders_of_its_own_episodes_only(tmp_path):
    mine, theirs = EPISODE, dataclasses.replace(EPISODE, start=1)  # shards of one folder
    for episode in (mine, theirs):
        planner_folder(episode, tmp_path).mkdir()
        (tmp_path / f".{planner_folder(episode, tmp_path).name}.k2x9_a").mkdir()  # its staging
    (tmp_path / BROKEN_DIR).mkdir()
    assert remove_staging(tmp_path, [mine]) == 2
    left = sorted(p.name for p in tmp_path.iterdir())
    theirs_folder = planner_folder(theirs, tmp_path).name
    assert left == sorted([BROKEN_DIR, theirs_folder, f".{theirs_folder}.k2x9_a"])
    assert remove_staging(tmp_path) == 2  # unsharded: every half-written folder


def damage_truncated_metrics(folder):
    text = (folder / "metrics.json").read_text()
    (folder / "metrics.json").write_text(text[: len(text) // 2])


def damage_missing_curves(folder):
    (folder / "curves.csv").unlink()


def damage_short_curves_row(folder):
    lines = (folder / "curves.csv").read_text().splitlines()
    lines[-1] = ",".join(lines[-1].split(",")[:2])  # a row cut short: no iou, no tu
    (folder / "curves.csv").write_text("\n".join(lines) + "\n")


def damage_other_method(folder):
    metrics = json.loads((folder / "metrics.json").read_text())
    (folder / "metrics.json").write_text(json.dumps({**metrics, "method": "mapex"}))


@pytest.mark.parametrize(
    ("damage", "config", "problem"),
    [
        (damage_truncated_metrics, SHORT, "unreadable"),
        (damage_missing_curves, SHORT, "unreadable"),
        (damage_short_curves_row, SHORT, "does not have 4 fields"),
        (damage_other_method, SHORT, "not generated:0/nearest"),
        (None, ExplorationConfig(steps=30), "another steps (20, not 30)"),
        (None, dataclasses.replace(SHORT, path_gain=dataclasses.replace(
            SHORT.path_gain, top_k=3)), "another path_gain.top_k"),
    ],
)  # fmt: skip
def test_a_broken_or_foreign_folder_is_moved_aside_and_run_again(
    tmp_path, sound_run, damage, config, problem, caplog
):
    shutil.copytree(sound_run, tmp_path / EPISODE.name)
    if damage is not None:
        damage(tmp_path / EPISODE.name)
    with caplog.at_level("WARNING"):
        assert not finished(EPISODE, tmp_path, plain(config))
    assert problem in caplog.text and "moved aside" in caplog.text
    assert not (tmp_path / EPISODE.name).exists()
    [aside] = (tmp_path / BROKEN_DIR).iterdir()
    assert aside.name.startswith(EPISODE.name)
    assert remove_staging(tmp_path) == 0  # the evidence is kept


def test_a_planner_writes_hidden_and_only_the_evaluation_publishes(tmp_path, sound_run):
    episode = EPISODE
    written = planner_folder(episode, tmp_path)
    assert written.parent == tmp_path and written.name.startswith(".")
    assert not publish(episode, tmp_path)  # the planner wrote nothing
    shutil.copytree(sound_run, written)
    assert not finished(episode, tmp_path)
    assert publish(episode, tmp_path) and finished(episode, tmp_path)
    assert not written.exists() and remove_staging(tmp_path) == 0


class FinishingSupervisor:
    """A stand-in for the supervisor: its one planner writes its folder and exits 0 a moment
    after it starts, and the Ctrl-C (`stop`) arrives in the same poll interval."""

    def __init__(self, sound_run, out, stop: threading.Event) -> None:
        self.services = ServicesConfig(supervision_poll_s=0.5)
        self.sound_run, self.out, self.stop = sound_run, out, stop
        self.codes: dict[str, int | None] = {}

    def start(self, spec) -> None:
        self.codes[spec.name] = None
        threading.Timer(0.05, self._finish, (spec.name,)).start()

    def _finish(self, name: str) -> None:
        shutil.copytree(self.sound_run, planner_folder(EPISODE, self.out))
        self.codes[name] = 0
        self.stop.set()  # SIGINT, in the very interval in which the planner finished

    def poll(self) -> None:
        pass

    def returncode(self, name: str) -> int | None:
        return self.codes.get(name)


def test_a_planner_that_finished_as_the_evaluation_was_interrupted_is_kept(tmp_path, sound_run):
    stop = threading.Event()
    supervisor = FinishingSupervisor(sound_run, tmp_path, stop)
    args = argparse.Namespace(jobs=1, out=tmp_path, no_progress=True)
    done, failures = run_episodes(supervisor, [EPISODE], args, [], NO_PROGRESS, stop)
    assert (done, failures) == (1, [])
    assert finished(EPISODE, tmp_path, plain(SHORT))  # published, not left hidden


class NoProgress:
    def of(self, _run_id: str) -> int:
        return 0


NO_PROGRESS = NoProgress()


def test_a_killed_and_resumed_evaluation_gives_the_same_table(tmp_path):
    """The evaluation whole (its own hub and pool) runs beside the killed and the resumed
    one: only its table is compared, at the end."""
    whole, resumed = tmp_path / "whole", tmp_path / "resumed"
    with open(tmp_path / "whole.log", "wb") as log:
        uninterrupted = evaluate(whole, "--no-report", log=log)
    try:
        with open(tmp_path / "killed.log", "wb") as log:
            first = evaluate(resumed, "--no-report", log=log)
            try:
                until(lambda: run_records(resumed), "a first published run", 300)
            finally:
                first.send_signal(signal.SIGKILL)
                first.wait(10)
        children = [int(pid) for pid in _started_pids(tmp_path / "killed.log")]
        until(lambda: not any(pid_alive(pid) for pid in children), "the orphans to stop", 30)
        published = run_records(resumed)
        with open(tmp_path / "resumed.log", "wb") as log:
            assert evaluate(resumed, log=log).wait(600) == 0
        assert uninterrupted.wait(600) == 0
    finally:
        if uninterrupted.poll() is None:
            uninterrupted.kill()
            uninterrupted.wait()
    after = run_records(resumed)
    assert {name: after[name] for name in published} == published  # kept, not run again
    logs = [tmp_path / name for name in ("whole.log", "killed.log", "resumed.log")]
    assert len(run_records(whole)) == 4
    resumed_table, whole_table = comparable_tables(run_records(resumed), run_records(whole))
    assert resumed_table == whole_table, pool_warnings(*logs)
    assert not list(resumed.glob(".*")), "a half-written run was left behind"
    report = json.loads((resumed / "report" / "report.json").read_text())
    assert report  # the report of the resumed evaluation was written
    invocations = (resumed / "evaluations.jsonl").read_text().splitlines()
    assert json.loads(invocations[-1])["episodes"] == 4


def _started_pids(log_path) -> list[str]:
    import re

    time.sleep(0.1)
    return re.findall(r"started \S+ \(pid (\d+)\)", log_path.read_text(errors="replace"))


BAD_ARGUMENTS = [
    (["--maps", "/no/such/map"], "no such map directory"),
    (["--maps", "generated:0", "--methods", "nearest,bogus"], "unknown method"),
    (["--maps", "generated:0", "--jobs", "0"], "--jobs must be at least 1"),
    (["--maps", "generated:0", "--steps", "-1"], "--steps must be at least 1"),
    (["--maps", "generated:0", "--steps", "1e3"], "--steps must be a whole number"),
    (["--maps", "generated:0", "--until-iou", "0"], "--until-iou must be in (0, 1]"),
    (["--maps", "generated:0", "--robots", "2"], "--robots 2 needs a team method"),
    (
        ["--maps", "generated:0", "--methods", "mapex_team", "--robots", "0"],
        "--robots must be at least 1",
    ),
    (["--maps", "generated:0", "--starts", "7"], "start poses 0-3"),
    (["--maps", "generated:0", "--set", "world.max_cells=1000"], "above the limit of 1,000"),
    (["--maps", "generated:0", "--starts-file", "{file}"], "map 'generated:0' needs a"),
    (["--maps", "generated:1", "--starts-file", "{walls}"], "no starts for map 'generated:1'"),
    (["--maps", "generated:0", "--starts-file", "{missing}"], "No such file"),
    (["--maps", "generated:0", "--starts-file", "{walls}"], "start cell (0, 0) is on a wall"),
    (["--maps", "generated:0", "--predictor", "classical"], "runs in one process only"),
    (
        ["--maps", "generated:0", "--predictor", "oracle", "--members", "g1"],
        "served by member g only",
    ),
]


@pytest.fixture(scope="module")
def bad_argument_runs(
    tmp_path_factory,
) -> dict[tuple[str, ...], tuple[Path, subprocess.CompletedProcess]]:
    """`python -m services.evaluate` with each of BAD_ARGUMENTS ({file}, {missing} and {walls}:
    starts files), all run at once (each only parses and fails), each with an --out and
    a hub port of its own: {args: (its --out, its run)}."""
    root = tmp_path_factory.mktemp("bad-arguments")
    (root / "bad.json").write_text('{"generated:0": [[1, 2, 3]]}')
    (root / "walls.json").write_text('{"generated:0": [[0, 0]]}')
    names = {"file": "bad.json", "missing": "none.json", "walls": "walls.json"}
    outs = [root / f"out-{k}" for k in range(len(BAD_ARGUMENTS))]
    cases = [
        ["services.evaluate", *(a.format(**{k: root / v for k, v in names.items()}) for a in args),
         "--out", str(out), "--listen", f"tcp/127.0.0.1:{free_loopback_port()}"]
        for (args, _), out in zip(BAD_ARGUMENTS, outs, strict=True)
    ]  # fmt: skip
    runs = zip(outs, run_python_m(cases), strict=True)
    return dict(zip((tuple(args) for args, _ in BAD_ARGUMENTS), runs, strict=True))


@pytest.mark.parametrize(("args", "message"), BAD_ARGUMENTS)
def test_bad_arguments_fail_in_one_line(args, message, bad_argument_runs):
    out, completed = bad_argument_runs[tuple(args)]
    assert completed.returncode == 2, completed.stderr
    assert message in completed.stderr.strip().splitlines()[-1]
    assert "Traceback" not in completed.stderr
    assert out.parent.exists() and not out.exists()


def test_a_bad_out_is_refused_before_any_episode(tmp_path):
    (tmp_path / "taken").write_text("a file")
    completed = subprocess.run(
        [sys.executable, "-m", "services.evaluate", "--maps", "generated:0",
         "--out", str(tmp_path / "taken")],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert completed.returncode == 2 and "Traceback" not in completed.stderr
    assert "cannot write results to" in completed.stderr.strip().splitlines()[-1]
    assert "episodes" not in completed.stderr  # found before any episode was planned to run
