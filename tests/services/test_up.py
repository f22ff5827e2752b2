"""`python -m services.up` end to end: real world, predictor and planner processes on loopback.

Each test starts up on a free loopback port (it serves the hub there), so tests never meet
the default hub tcp/127.0.0.1:7447 nor each other. Every process is killed at teardown.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
import torch
from commands_at_once import run_python_m
from service_processes import (
    REPO_ROOT,
    STOP_DEADLINE_S,
    free_loopback_port,
    kill_router,
    spawn_router,
    until,
    wait_router_ready,
)
from up_processes import UpProcess, pid_alive, read_run

from mapex.budget import auto_steps, resolve_steps
from mapex.config import ExplorationConfig, apply_overrides
from mapex.episode import run_episode
from mapex.prediction.learned import LearnedEnsemble
from mapex.prediction.oracle import OraclePredictor
from mapex.results import write_results
from mapex.team.starts import team_start_cells
from mapex.worlds import load_world
from mapex.worlds.starts import eligible_start_cells
from services.codec import DEFAULT_SERVICES, SCHEMA_VERSION
from services.config import RunConfig
from services.keys import (
    ROBOT_TOPICS,
    alive_planner_key,
    alive_predictor_pattern,
    parse_key,
    predict_key,
    robot_key,
    run_key,
)
from services.messages import ErrorReply, PoseMessage, StepRequest, decode_message
from services.pool import resolve_pool_predictor
from services.serving import RUN_TOKEN_ENV
from services.supervisor import ProcessSpec, Supervisor, parse_tcp_endpoint
from services.up import build_parser, child_specs, plan_runs, supervise
from services.zenoh_config import open_session, zenoh_config

WORLD = "generated:0"


def in_process_run(method: str, steps: int, tmp_path, start=0):
    """The same episode in one process, with one torch thread like a worker, written out."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        world = load_world(WORLD)
        config = ExplorationConfig(steps=steps)
        result = run_episode(world, method, LearnedEnsemble(), start, 0, config)
    finally:
        torch.set_num_threads(threads)
    return read_run(write_results(result, world, tmp_path / "in_process"))


def start_up(tmp_path, name: str, *args: str) -> tuple[UpProcess, str]:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    up = UpProcess(
        tmp_path / f"{name}.log", "--world", WORLD, "--listen", endpoint,
        "--run-prefix", name, "--out", str(tmp_path / "runs"), *args,
    )  # fmt: skip
    return up, endpoint


def spawn_watch(tmp_path, endpoint: str, run: str) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "services.watch", "--run", run, "--connect", endpoint,
        "--png", str(tmp_path / "watch.png"), "--gif", str(tmp_path / "watch.gif"),
        "--until-finished", "--every-s", "0.5", "--timeout-s", "400",
    ]  # fmt: skip
    log = open(tmp_path / "watch.log", "wb")  # noqa: SIM115 (closed with the process)
    return subprocess.Popen(command, cwd=REPO_ROOT, stdout=log, stderr=log)


def watch_exit_code(watch: subprocess.Popen, timeout_s: float) -> int | None:
    """The viewer's exit code, or None if it is still running after `timeout_s`."""
    try:
        return watch.wait(timeout_s)
    except subprocess.TimeoutExpired:
        return None


def middle_start_cell() -> tuple[int, int]:
    """An eligible start cell of WORLD in the middle of the list, not one of its corners."""
    cells = np.argwhere(eligible_start_cells(load_world(WORLD), 3))
    return tuple(int(v) for v in cells[len(cells) // 2])


def test_distributed_run_equals_in_process_run_and_a_viewer_sees_its_maps(tmp_path):
    """120 steps: several re-plans, G's metric samples at 0, 50 and 100, and TU at 0 and 100
    (each a query of the pool, or of the in-process ensemble)."""
    steps, start = 120, middle_start_cell()
    up, endpoint = start_up(
        tmp_path, "same", "--method", "mapex", "--steps", str(steps),
        "--start", f"{start[0]},{start[1]}",
    )  # fmt: skip
    watch = None
    try:
        watch = spawn_watch(tmp_path, endpoint, "same-0")
        assert up.wait() == 0, up.log()
        assert watch_exit_code(watch, 60) == 0, (tmp_path / "watch.log").read_text()
    finally:
        up.kill()
        if watch is not None and watch.poll() is None:
            watch.kill()
    metrics, trajectory, curves = read_run(tmp_path / "runs" / "same-0-r0")
    expected_metrics, expected_trajectory, expected_curves = in_process_run(
        "mapex", steps, tmp_path, start
    )
    assert metrics["start_index"] is None and tuple(metrics["start"]) == start
    np.testing.assert_array_equal(trajectory, expected_trajectory)
    assert curves == expected_curves
    assert metrics["auc"] == expected_metrics["auc"] and metrics["replans"] > 1
    assert metrics["degraded_steps"] == [] and metrics["degraded_metric_samples"] == []
    audit = metrics["member_workers"]  # who answered every member query, for an audit
    assert len(audit["replans"]) == metrics["replans"] and audit["metric_samples"]
    workers = {member: f"up{up.process.pid}-{member}-0" for member in ("g", "g1", "g2", "g3")}
    members_read = {m: workers[m] for m in ("g1", "g2", "g3")}  # mapex never reads G's map
    assert all(served == members_read for _, served in audit["replans"])
    assert all(served == {"g": workers["g"]} for _, served in audit["metric_samples"])
    assert expected_metrics["member_workers"] == {"replans": [], "metric_samples": []}
    watch_log = (tmp_path / "watch.log").read_text()
    for kind in ("observed_map", "prediction/mean", "prediction/variance"):
        assert kind in watch_log, watch_log
    assert (tmp_path / "watch.png").stat().st_size > 0
    assert (tmp_path / "watch.gif").stat().st_size > 0


def test_a_distributed_oracle_run_equals_the_in_process_one(tmp_path):
    """One oracle worker (member g) reads the run's ground truth from the world; the planner
    checks each answer against its own and gets the very run of `mapex run --predictor
    oracle`, every re-plan answered by that worker."""
    steps = 80
    up, _ = start_up(tmp_path, "oracle", "--predictor", "oracle", "--steps", str(steps))
    try:
        assert up.wait() == 0, up.log()
    finally:
        up.kill()
    metrics, trajectory, curves = read_run(tmp_path / "runs" / "oracle-0-r0")
    world = load_world(WORLD)
    result = run_episode(
        world, "mapex", OraclePredictor(world.occupancy), 0, 0, ExplorationConfig(steps=steps)
    )
    expected_metrics, expected_trajectory, expected_curves = read_run(
        write_results(result, world, tmp_path / "in_process")
    )
    np.testing.assert_array_equal(trajectory, expected_trajectory)
    assert curves == expected_curves and metrics["auc"] == expected_metrics["auc"]
    assert metrics["predictor"] == expected_metrics["predictor"] == "oracle"
    assert metrics["degraded_steps"] == [] and metrics["degraded_metric_samples"] == []
    assert set(up.children()) == {"predictor-g", "world-oracle-0", "planner-oracle-0-r0"}
    worker = {"g": f"up{up.process.pid}-g-0"}
    assert (
        metrics["replans"] > 1 and len(metrics["member_workers"]["replans"]) == metrics["replans"]
    )
    assert all(served == worker for _, served in metrics["member_workers"]["replans"])
    assert "the ground truth is the prediction" in up.log()


@pytest.mark.parametrize(
    "method",
    [
        "mapex_team",  # claims
        pytest.param("mapex_assign", marks=pytest.mark.slow),  # teammates' poses and claims
        pytest.param("mapex_voronoi", marks=pytest.mark.slow),  # teammates' poses
    ],
)
def test_a_team_through_services_up_equals_the_in_process_team(tmp_path, method):
    """The robots start side by side, so claims and poses steer them from the first re-plan:
    100 steps are several re-plans each, with the snapshot taken at the last step."""
    steps = 100
    snapshot = f"metrics.snapshot_steps={steps}"
    up, _ = start_up(tmp_path, "team", "--method", method, "--robots", "2",
                     "--steps", str(steps), "--set", snapshot)  # fmt: skip
    try:
        assert up.wait() == 0, up.log()
    finally:
        up.kill()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        world = load_world(WORLD)
        config = apply_overrides(ExplorationConfig(steps=steps), [snapshot])
        expected = run_episode(world, method, LearnedEnsemble(), 0, 0, config, robots=2)
    finally:
        torch.set_num_threads(threads)
    for robot in (0, 1):
        folder = tmp_path / "runs" / f"team-0-r{robot}"
        metrics, _, curves = read_run(folder)
        rows = np.loadtxt(folder / "trajectories.csv", delimiter=",", skiprows=1, dtype=np.int64)
        for mate in (0, 1):  # every planner knows where every robot went
            path = rows[rows[:, 1] == mate][:, 2:]
            np.testing.assert_array_equal(path, expected.trajectories[mate])
        assert metrics["auc"] == {k: round(v, 6) for k, v in expected.curves.auc().items()}
        assert [float(row[1]) for row in curves[1:]] == pytest.approx(
            expected.curves.coverage, abs=1e-6
        )
        with np.load(folder / "snapshots.npz") as snapshots:
            assert list(snapshots["steps"]) == [steps]
            np.testing.assert_array_equal(snapshots["observed"][0], expected.snapshots[steps][0])
        assert metrics["team"]["overlap"] == round(expected.overlap, 4)


SETTINGS = ["motion.cells_per_step=2", "services.predict_timeout_s=20"]
HANDED_ON = ["motion.cells_per_step=2", "services.predict_timeout_s=20.0"]  # as handed on


def up_plan(*flags: str) -> tuple[argparse.Namespace, RunConfig, list]:
    """services.up's arguments, run configuration and runs for `flags`, as its main has them."""
    args = build_parser().parse_args(["--world", WORLD, "--run-prefix", "plan", *flags])
    run_config = RunConfig(ExplorationConfig(until_iou=args.until_iou))
    run_config = run_config.with_overrides(args.overrides)
    world = load_world(args.world)
    exploration = dataclasses.replace(
        run_config.exploration, steps=resolve_steps(args.steps, world)
    )
    run_config = dataclasses.replace(run_config, exploration=exploration)
    return args, run_config, plan_runs(args, world, exploration)


def set_flags(items: list[str]) -> list[str]:
    return [flag for item in items for flag in ("--set", item)]


def test_every_child_gets_the_run_s_settings_on_its_command_line():
    team = ["--steps", "40", "--robots", "2", "--members", "g,g2"]
    args, run_config, runs = up_plan(*team, *set_flags(SETTINGS))
    flags = ["--connect", "tcp/127.0.0.1:1"]
    specs = child_specs(args, runs, flags, run_config)
    assert [len(specs[role]) for role in ("workers", "worlds", "planners")] == [2, 1, 2]
    for spec in specs["workers"] + specs["worlds"] + specs["planners"]:
        pairs = list(zip(spec.args, spec.args[1:], strict=False))
        for item in ["steps=40", *HANDED_ON]:
            assert ("--set", item) in pairs, (spec.name, spec.args)
        assert spec.args[-2:] == tuple(flags)  # the Zenoh flags come last
        assert runs[0].token not in spec.args  # the run's secret is in the environment
    for spec in specs["worlds"] + specs["planners"]:
        assert spec.env == {RUN_TOKEN_ENV: runs[0].token}, spec  # theirs only
        assert not spec.restart, spec  # a world that dies ends its run; planners finish
    assert all(spec.restart and not spec.env for spec in specs["workers"])
    items = [b for a, b in zip(spec.args, spec.args[1:], strict=False) if a == "--set"]
    assert RunConfig().with_overrides(items) == run_config  # each child rebuilds the run's


def test_the_chosen_predictor_reaches_every_worker_and_planner_and_the_oracle_is_one_worker():
    args, run_config, runs = up_plan("--predictor", "lama-v2")
    specs = child_specs(args, runs, [], run_config)
    for spec in specs["workers"] + specs["planners"]:
        assert spec.args[spec.args.index("--predictor") + 1] == "lama-v2", spec.args
    args, run_config, runs = up_plan()  # the default's command lines are as they were
    assert all(
        "--predictor" not in spec.args
        for role in child_specs(args, runs, [], run_config).values()
        for spec in role
    )
    args, run_config, runs = up_plan("--predictor", "oracle")
    resolve_pool_predictor(args)
    specs = child_specs(args, runs, [], run_config)
    assert [spec.name for spec in specs["workers"]] == ["predictor-g"]
    assert "--threads" not in specs["workers"][0].args


def test_a_team_of_any_method_deploys_around_the_start_and_runs_go_round_the_corners():
    args, run_config, runs = up_plan("--method", "nearest", "--robots", "2", "--start", "1")
    world = load_world(WORLD)
    (run,) = runs
    assert list(run.starts) == team_start_cells(world, [1], 2, run_config.exploration)
    assert run.starts[0] != run.starts[1] and 1 not in run.starts  # cells, not corners 1, 2
    _, _, alone = up_plan("--method", "nearest", "--runs", "3", "--start", "3")
    assert [run.starts for run in alone] == [(3,), (0,), (1,)]
    assert len({run.token for run in alone}) == 3 and [run.seed for run in alone] == [0, 1, 2]


def test_set_reaches_the_world_and_every_process_of_an_up_run(tmp_path):
    """`--set motion.cells_per_step=2` moves the robot 2 cells a step (the world simulated
    it, the planner agreed to it); `--set services.predict_timeout_s=20` is what the
    planner, the world and the worker say they run with, and what the planner used. The
    planner waits for g1-g3, which never come (`--members g`), only a second."""
    sets = set_flags([*SETTINGS, "services.predict_max_cells=1000", "services.workers_wait_s=1"])
    up, _ = start_up(
        tmp_path, "set", "--method", "nearest", "--steps", "40", "--members", "g", *sets
    )
    try:
        assert up.wait() == 0, up.log()
    finally:
        up.kill()
    metrics, trajectory, _ = read_run(tmp_path / "runs" / "set-0-r0")
    assert len(trajectory) == 41
    assert np.abs(np.diff(trajectory, axis=0)).max() == 2  # Chebyshev: 2 cells, not 3
    assert metrics["config"]["motion"]["cells_per_step"] == 2
    assert "within 20 s" in metrics["degraded_from_start"]  # the planner's own timeout
    said = dict(re.findall(r"\[([a-z0-9_-]+)\][^\n]* INFO (settings: [^\n]*)", up.log()))
    assert {"planner-set-0-r0", "world-set-0", "predictor-g"} <= set(said), up.log()
    for name, line in said.items():
        assert all(f" {item}" in line for item in HANDED_ON), (name, line)


def kill_child_at_step(up: UpProcess, endpoint: str, run: str, child: str, step: int) -> None:
    """SIGKILL `up`'s child named `child` once robot r0 of `run` has reached `step`."""
    session = open_session(zenoh_config(connect=[endpoint], listen=[]))
    steps = []
    subscriber = session.declare_subscriber(
        robot_key(run, "r0", "pose"),
        lambda sample: steps.append(PoseMessage.decode(sample.payload.to_bytes()).t),
    )
    try:
        until(lambda: steps and steps[-1] >= step, f"the run to reach step {step}", 300)
        os.kill(up.children()[child][0], signal.SIGKILL)
    finally:
        subscriber.undeclare()
        session.close()


KILL_STEPS = 400  # the run whose worker is killed at step KILL_AT: long past the restart
KILL_AT = 100


def test_a_worker_killed_mid_run_is_restarted_and_the_run_completes(tmp_path):
    up, endpoint = start_up(tmp_path, "kill", "--method", "mapex", "--steps", str(KILL_STEPS))
    try:
        kill_child_at_step(up, endpoint, "kill-0", "predictor-g", KILL_AT)
        assert up.wait() == 0, up.log()
    finally:
        up.kill()
    metrics, trajectory, curves = read_run(tmp_path / "runs" / "kill-0-r0")
    assert metrics["steps"] == KILL_STEPS and int(curves[-1][0]) == KILL_STEPS
    assert len(trajectory) == KILL_STEPS + 1 or metrics["finished_at"] is not None
    degraded = metrics["degraded_steps"] + metrics["degraded_metric_samples"]
    assert degraded and min(degraded) >= KILL_AT, metrics
    audit = dict(map(tuple, metrics["member_workers"]["replans"]))
    assert all("g" not in audit[t] and len(audit[t]) == 3 for t in metrics["degraded_steps"])
    assert "predictor-g exited with -9 (SIGKILL); restarted (1/" in up.log()
    assert len(up.children()["predictor-g"]) == 2


def test_a_team_goes_on_without_a_killed_planner_and_marks_its_robot_lost(tmp_path):
    up, endpoint = start_up(tmp_path, "tkill", "--method", "nearest_team", "--robots", "2",
                            "--steps", "300")  # fmt: skip
    try:
        kill_child_at_step(up, endpoint, "tkill-0", "planner-tkill-0-r1", 50)
        assert up.wait() == 1, up.log()  # a planner failed; the team's run went on
    finally:
        up.kill()
    metrics, _, curves = read_run(tmp_path / "runs" / "tkill-0-r0")
    assert int(curves[-1][0]) == 300
    lost_at = metrics["team"]["lost_at"]
    assert list(lost_at) == ["r1"] and 50 <= lost_at["r1"] < 300, lost_at
    rows = np.loadtxt(tmp_path / "runs" / "tkill-0-r0" / "trajectories.csv", delimiter=",",
                      skiprows=1, dtype=np.int64)  # fmt: skip
    lost_path = rows[rows[:, 1] == 1][:, 2:]
    assert (lost_path[lost_at["r1"] + 1 :] == lost_path[-1]).all()  # it stood still since
    assert "robot r1 is lost: its planner is gone" in up.log()
    assert not (tmp_path / "runs" / "tkill-0-r1").exists()


def test_a_world_killed_mid_run_ends_the_run_at_once_naming_it(tmp_path):
    up, endpoint = start_up(tmp_path, "wkill", "--method", "nearest", "--steps", "1000")
    try:
        kill_child_at_step(up, endpoint, "wkill-0", "world-wkill-0", 50)
        killed_at = time.monotonic()
        assert up.wait(60) == 1, up.log()
        ended_s = time.monotonic() - killed_at
    finally:
        up.kill()
    assert ended_s < 15, ended_s  # not the planner's whole step wait
    assert "world-wkill-0 exited with -9 (SIGKILL) before its run ended" in up.log()
    assert not (tmp_path / "runs" / "wkill-0-r0").exists()
    for pids in up.children().values():
        assert not any(pid_alive(pid) for pid in pids)


class NoProgress:
    def of(self, run: str) -> int:
        return 0


def test_a_child_failing_to_start_ends_the_run_at_once_with_its_line(caplog):
    """A worker that exits 2 (e.g. no weights) is not restarted and ends everything."""
    helpers = str(REPO_ROOT / "tests" / "helpers")

    def child(name: str, *args: str, restart: bool = False) -> ProcessSpec:
        return ProcessSpec(name, "supervised_child", args, restart=restart, cwd=helpers)

    specs = {
        "workers": [child("predictor-g", "--say", "error: no weights file g.pt", "--exit", "2",
                          restart=True)],
        "worlds": [child("world-x", "--sleep", restart=False)],
        "planners": [child("planner-x", "--sleep")],
    }  # fmt: skip
    lines: list[str] = []
    with Supervisor(lines.append) as supervisor:
        for spec in specs["workers"] + specs["worlds"] + specs["planners"]:
            supervisor.start(spec)
        began = time.monotonic()
        code = supervise(supervisor, specs, NoProgress(), [], 1, threading.Event(), False)
        ended_s = time.monotonic() - began
        assert supervisor.is_running("planner-x")  # ended by supervise, not by itself
    assert code == 1 and ended_s < 10, (code, ended_s)
    assert (
        "[supervisor] predictor-g exited with 2; not restarted: a usage error would repeat" in lines
    )
    assert supervisor.restarts == {}
    assert "predictor-g failed to start (error: no weights file g.pt)" in caplog.text


def test_ctrl_c_leaves_no_process_behind(tmp_path):
    up, endpoint = start_up(tmp_path, "stop", "--method", "nearest", "--steps", "1000")
    try:
        until(lambda: "planner-stop-0-r0" in up.children(), "up to start its children", 60)
        time.sleep(3.0)  # let the children get going (imports, sessions)
        children = [pid for pids in up.children().values() for pid in pids]
        up.interrupt()
        began = time.monotonic()
        assert up.wait(STOP_DEADLINE_S + 5) == 130
        until(
            lambda: not any(pid_alive(pid) for pid in children),
            "every child to exit",
            max(STOP_DEADLINE_S - (time.monotonic() - began), 0.5),
        )
    finally:
        up.kill()


def test_services_joined_only_through_a_router_run_an_episode(tmp_path):
    router_endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = spawn_router(tmp_path, router_endpoint)
    try:
        wait_router_ready(router)  # a client that finds no router gives up at once
    except BaseException:
        kill_router(router)
        raise
    up = UpProcess(
        tmp_path / "routed.log", "--world", WORLD, "--mode", "client", "--connect",
        router_endpoint, "--run-prefix", "routed", "--out", str(tmp_path / "runs"),
        "--method", "mapex", "--steps", "60",
    )  # fmt: skip
    try:
        assert up.wait() == 0, up.log()
    finally:
        up.kill()
        router.process.send_signal(signal.SIGINT)
        router.process.wait(STOP_DEADLINE_S)
        kill_router(router)
    metrics, trajectory, _ = read_run(tmp_path / "runs" / "routed-0-r0")
    assert len(trajectory) == 61 and metrics["degraded_steps"] == []


def test_an_auto_budget_run_ends_once_gs_iou_reaches_the_level(tmp_path):
    up, _ = start_up(
        tmp_path, "stop", "--method", "nearest", "--steps", "auto", "--until-iou", "0.3"
    )
    try:
        assert up.wait() == 0, up.log()
    finally:
        up.kill()
    metrics, _, _ = read_run(tmp_path / "runs" / "stop-0-r0")
    assert metrics["steps"] == auto_steps(load_world(WORLD))
    assert metrics["end_reason"] == "iou_reached" and metrics["finished_at"] < 1000
    assert metrics["reached"]["iou"]["0.9"] is None  # censored: it stopped at 0.3
    assert metrics["config"]["until_iou"] == 0.3


BAD_FLAGS = [
    (["--steps", "0"], "--steps must be at least 1"),
    (["--steps", "lots"], "--steps must be a whole number or 'auto'"),
    (["--until-iou", "2"], "--until-iou must be in (0, 1]"),
    (["--until-iou", "x"], "--until-iou must be a number in (0, 1]"),
    (["--world", "/no/such/map"], "error"),
    (["--members", "g,g9"], "unknown member"),
    (["--run-prefix", "Bad Id"], "--run-prefix"),
    (["--set", "sensor.nope=1"], "error"),
    (["--start", "4"], "corners are 0-3"),
    (["--start", "0,0"], "world 'generated:0': start cell (0, 0) is on a wall"),
    (["--start", "0,0", "--robots", "2"], "start cell (0, 0) is on a wall"),
    (["--robots", "3", "--set", "team.spacing_cells=5000"], "room for 1 robots 5000 cells"),
    (["--set", "services.nope=1"], "override 'services.nope=1': unknown field 'nope'"),
    (["--out", "README.md"], "cannot write results to README.md: it is a file"),
    (["--set", "world.max_cells=1000"], "--set world.max_cells="),
    (["--predictor", "classical"], "--predictor classical runs in one process only"),
    (["--predictor", "oracle", "--members", "g,g1"], "served by member g only"),
]


@pytest.fixture(scope="module")
def bad_flag_runs() -> dict[tuple[str, ...], subprocess.CompletedProcess]:
    """`python -m services.up` with each of BAD_FLAGS, all run at once (each only parses
    and fails), each serving its hub on a port of its own so that none meets another."""
    cases = [
        ["services.up", *args, "--listen", f"tcp/127.0.0.1:{free_loopback_port()}"]
        for args, _ in BAD_FLAGS
    ]
    return dict(zip((tuple(args) for args, _ in BAD_FLAGS), run_python_m(cases), strict=True))


@pytest.mark.parametrize(("args", "message"), BAD_FLAGS)
def test_bad_flags_fail_in_one_line(args, message, bad_flag_runs):
    completed = bad_flag_runs[tuple(args)]
    assert completed.returncode == 2
    lines = completed.stderr.strip().splitlines()
    assert message in lines[-1] and "Traceback" not in completed.stderr


def malformed_payloads() -> dict[str, bytes]:
    """One payload per kind of damage DESIGN.md names (none of them a valid step)."""
    observed = np.full((4, 5), 1, dtype=np.float32)  # a map of the wrong dtype
    wrong_dtype = msgpack.packb(
        {"schema": SCHEMA_VERSION, "type": "predict_request", "request_id": 1,
         "observed": {"dtype": "float32", "shape": [4, 5], "zlib": False,
                      "data": observed.tobytes()}},
    )  # fmt: skip
    wrong_shape = msgpack.packb(
        {"schema": SCHEMA_VERSION, "type": "step_request", "seq": 10**6,
         "cells": {"dtype": "int32", "shape": [3, 3, 3], "zlib": False,
                   "data": bytes(3 * 3 * 3 * 4)}},
    )  # fmt: skip
    return {
        "random bytes": np.random.default_rng(0).bytes(300),
        "wrong schema": msgpack.packb({"schema": SCHEMA_VERSION + 1, "type": "step_request"}),
        "wrong dtype": wrong_dtype,
        "wrong shape": wrong_shape,
        "oversized": bytes(DEFAULT_SERVICES.max_message_bytes + 1),
    }


def attack(session, run: str) -> list[str]:
    """Send every malformed payload to every queryable and subscribed key of `run`."""
    keys = [run_key(run, "world_info"), run_key(run, "ground_truth")]
    keys += [robot_key(run, "r0", topic) for topic in ROBOT_TOPICS]
    for reply in session.liveliness().get(alive_predictor_pattern(), timeout=2.0):
        alive = parse_key(str(reply.ok.key_expr))
        keys.append(predict_key(alive.member, alive.worker_id))
    assert any("/predict/" in key for key in keys)
    for payload in malformed_payloads().values():
        for key in keys:
            session.put(key, payload)
            list(session.get(key, payload=payload, timeout=5.0))
    return keys


def step_without_token(session, run: str, seq: int) -> str:
    """A well-formed step of robot r0 from a client that lacks the run's token: the reply."""
    request = StepRequest(seq, np.array([[1, 1]], dtype=np.int32), False, False, None, None, None)
    key = robot_key(run, "r0", "step")
    (reply,) = session.get(key, payload=request.encode(), timeout=5.0)
    sample = reply.ok if reply.ok is not None else reply.err  # a signed world replies "ok"
    return decode_message(sample.payload.to_bytes(), (ErrorReply,)).message


def test_malformed_payloads_harm_no_process_and_no_result(tmp_path):
    steps = 300
    up, endpoint = start_up(tmp_path, "bad", "--method", "nearest", "--steps", str(steps))
    session = open_session(zenoh_config(connect=[endpoint], listen=[]))
    watch = spawn_watch(tmp_path, endpoint, "bad-0")
    try:
        until(lambda: "planner-bad-0-r0" in up.children(), "up to start its children", 60)
        until(
            lambda: list(session.liveliness().get(alive_planner_key("bad-0", "r0"), timeout=1.0)),
            "the planner to start",
            120,
        )
        until(
            lambda: (
                len(list(session.liveliness().get(alive_predictor_pattern(), timeout=1.0))) == 4
            ),
            "the four workers to start",
            120,
        )
        stray_steps = [step_without_token(session, "bad-0", seq) for seq in (0, 1, 5, 50)]
        attack(session, "bad-0")
        assert up.wait() == 0, up.log()
        assert watch_exit_code(watch, 60) == 0, (tmp_path / "watch.log").read_text()
    finally:
        session.close()
        up.kill()
        if watch.poll() is None:
            watch.kill()
    log = up.log()
    assert "restarted" not in log and "Traceback" not in log, log
    metrics, trajectory, curves = read_run(tmp_path / "runs" / "bad-0-r0")
    expected_metrics, expected_trajectory, expected_curves = in_process_run(
        "nearest", steps, tmp_path
    )
    np.testing.assert_array_equal(trajectory, expected_trajectory)
    assert curves == expected_curves and metrics["auc"] == expected_metrics["auc"]
    for refusal in ("refused a malformed step request", "refused a malformed request", "exceeds"):
        assert refusal in log
    assert all("without this run's token" in reply for reply in stray_steps), stray_steps
    assert "dropped a malformed" in (tmp_path / "watch.log").read_text()


def test_two_runs_share_a_pool_of_replicas_and_every_replica_works(tmp_path):
    up, _ = start_up(
        tmp_path, "pool", "--method", "mapex", "--steps", "60", "--runs", "2", "--replicas", "2"
    )
    try:
        assert up.wait() == 0, up.log()
    finally:
        up.kill()
    log = up.log()
    answered = {
        name: int(count)
        for name, count in re.findall(r"\[(predictor-g\d?-\d)\].*answering (\d+) queries", log)
    }
    assert len(answered) == 8 and all(answered.values()), answered  # both replicas of each
    first, second = (read_run(tmp_path / "runs" / f"pool-{k}-r0") for k in (0, 1))
    assert first[0]["start_index"] == 0 and second[0]["start_index"] == 1
    for metrics, _, _ in (first, second):
        assert metrics["degraded_steps"] == [] and metrics["degraded_metric_samples"] == []


HUB = DEFAULT_SERVICES.hub_endpoint


@pytest.mark.parametrize("command", ["services.up", "services.evaluate"])
def test_a_taken_default_hub_is_refused_up_front_with_the_ways_out(command, tmp_path):
    """Joining another supervisor's hub silently would lose this run when that one ends."""
    hub = socket.socket()
    hub.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        hub.bind(parse_tcp_endpoint(HUB))  # or something already listens there: the same
        hub.listen()
    except OSError:
        pass
    try:
        completed = subprocess.run(
            [sys.executable, "-m", command, "--steps", "5", "--out", str(tmp_path / "out"),
             *(["--maps", "generated:0"] if command == "services.evaluate" else [])],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        hub.close()
    assert completed.returncode == 2 and "Traceback" not in completed.stderr
    last = completed.stderr.strip().splitlines()[-1]
    assert f"a hub already listens on {HUB}" in last
    assert "--listen" in last and "--connect" in last
