"""`services.evaluate --shard K/N` for real: bad values are one line and exit 2, shards that
share a folder must be of one campaign, and an experiment run as 3 shard processes (into
folders of their own, each with its own pool, all at once; and into one shared folder on
one shared predictor pool) and merged by `python -m mapex.report` equals it run whole."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from commands_at_once import run_python_m
from service_processes import (
    REPO_ROOT,
    ServiceProcesses,
    free_loopback_port,
    kill_router,
    spawn_router,
    wait_router_ready,
)
from shard_runs import (
    CAMPAIGN,
    any_degraded,
    comparable_tables,
    evaluate_case,
    evaluate_command,
    pool_warnings,
    run_commands,
    run_records,
    shard_commands,
)

from mapex.prediction.base import MEMBER_NAMES
from mapex.results import CAMPAIGN_FILE
from mapex.shards import Shard, shard_items
from services.evaluate import build_parser, plan_episodes

WORKER_START_DEADLINE_S = 120.0  # four torch workers loading on a loaded 2-core machine


def run(command: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(command, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)


BAD_SHARDS = ["3/3", "-1/2", "a/b", "0/0", "1", "2/1", "", "1/2/3", "99999999999/100000000000"]


@pytest.fixture(scope="module")
def bad_shard_runs(tmp_path_factory) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """The evaluation with each of BAD_SHARDS, all run at once (each only parses and fails),
    each with an --out of its own: {value: (its --out, its run)}."""
    root = tmp_path_factory.mktemp("bad-shards")
    outs = [root / f"out-{k}" for k in range(len(BAD_SHARDS))]
    cases = [
        evaluate_case(out, f"--shard={value}") for value, out in zip(BAD_SHARDS, outs, strict=True)
    ]
    return dict(zip(BAD_SHARDS, zip(outs, run_python_m(cases), strict=True), strict=True))


@pytest.mark.parametrize("value", BAD_SHARDS)
def test_a_bad_shard_is_one_line_and_exit_2(value, bad_shard_runs):
    out, completed = bad_shard_runs[value]
    assert completed.returncode == 2, completed.stderr
    lines = completed.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("services.evaluate: error: --shard"), lines
    assert out.parent.exists() and not out.exists()


def test_shards_that_share_a_folder_must_be_of_one_campaign(tmp_path):
    out = tmp_path / "shared"
    # 4 episodes in 6 shards: shards 4 and 5 have none, so nothing runs here
    for empty in ("5/6", "4/6"):
        completed = run(evaluate_command(out, "--shard", empty))
        assert completed.returncode == 0, completed.stderr
    assert json.loads((out / CAMPAIGN_FILE).read_text())["shards"] == 6
    assert json.loads((out / "evaluations.jsonl").read_text().splitlines()[-1])["shard"] == "4/6"
    other_steps = [*CAMPAIGN[:-1], "40"]
    refused = [
        (evaluate_case(out, "--shard", "5/7"), "split into 6 shard(s), not 7"),
        (evaluate_case(out, "--shard", "5/6", "--set", "motion.cells_per_step=2"),
         "another motion.cells_per_step (3, not 2)"),
        (evaluate_case(out, "--shard", "5/6", campaign=other_steps), "60 steps, not 40"),
        (evaluate_case(out), "split into 6 shard(s), not 1"),  # the whole, unsharded
    ]  # fmt: skip
    runs = run_python_m([case for case, _ in refused])  # none writes: they may run at once
    for (_, problem), completed in zip(refused, runs, strict=True):
        assert completed.returncode == 2, completed.stderr
        lines = completed.stderr.strip().splitlines()
        assert len(lines) == 1 and problem in lines[0] and "another --out" in lines[0], lines
    assert sorted(p.name for p in out.iterdir()) == [CAMPAIGN_FILE, "evaluations.jsonl"]


def shards_of(count: int) -> list[set[str]]:
    """The episode names of each shard of CAMPAIGN, as services.evaluate deals them."""
    args = build_parser().parse_args(list(CAMPAIGN))
    episodes = plan_episodes(args.maps, args.methods, args.starts, args.seeds, steps=args.steps)
    return [
        {e.name for e in shard_items(episodes, Shard(k, count), lambda e: e.method)}
        for k in range(count)
    ]


def start_pool(tmp_path) -> tuple:
    """A router and one predictor worker per member, as a cluster's shared pool."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = spawn_router(tmp_path, endpoint)
    wait_router_ready(router)
    pool = ServiceProcesses(endpoint, tmp_path)
    for member in MEMBER_NAMES:
        pool.spawn(f"worker-{member}", "services.predictor", "--member", member, "--mode", "client")
    for member in MEMBER_NAMES:
        name = f"worker-{member}"
        pool.wait_until_announced(
            name, lambda n=name: "serving member" in pool.log_of(n), WORKER_START_DEADLINE_S
        )
    return router, pool, endpoint


def report(*args: str) -> None:
    completed = run([sys.executable, "-m", "mapex.report", *args])
    assert completed.returncode == 0, completed.stderr


def test_an_experiment_run_in_shards_and_merged_equals_it_run_whole(tmp_path):
    whole = tmp_path / "whole"
    # three shards at once on this machine, each with its own workers and its own hub
    separate = [tmp_path / f"shard-{k}" for k in range(3)]
    assert run_commands(shard_commands(separate, 3), tmp_path, "separate") == [0, 0, 0]
    # three shards at once into one folder, on one shared pool (`--members none`), and
    # beside them the experiment whole, with its own workers and hub
    shared = tmp_path / "shared"
    router, pool, endpoint = start_pool(tmp_path)
    try:
        joined = ("--mode", "client", "--connect", endpoint, "--members", "none")
        listen = f"tcp/127.0.0.1:{free_loopback_port()}"
        commands = [
            *shard_commands(shared, 3, *joined),
            evaluate_command(whole, "--listen", listen),
        ]
        assert run_commands(commands, tmp_path, "shared+whole") == [0, 0, 0, 0]
    finally:
        pool.kill_all()
        kill_router(router)
    logs = sorted(tmp_path.glob("*.log"))

    dealt = shards_of(3)
    assert [len(names) for names in dealt] == [2, 1, 1]
    assert [set(run_records(folder)) for folder in separate] == dealt  # each ran its own
    expected = run_records(whole)
    assert set(expected) == set().union(*dealt) and len(expected) == 4
    merged = {name: r for folder in separate for name, r in run_records(folder).items()}
    for table in (merged, run_records(shared)):
        sharded, unsharded = comparable_tables(table, expected)
        assert sharded == unsharded, pool_warnings(*logs)
    assert not list(shared.glob(".*")), "a half-written run was left behind"
    assert len((shared / "evaluations.jsonl").read_text().splitlines()) == 3
    assert not (shared / "report").exists()  # a shard writes no report

    report(*map(str, separate), "--out", str(tmp_path / "merged"))
    report(str(shared))
    tables = [
        json.loads((folder / "report.json").read_text())
        for folder in (whole / "report", tmp_path / "merged", shared / "report")
    ]
    if any_degraded(expected, merged, run_records(shared)):  # only coverage is sure
        tables = [{m: row["auc"]["coverage"] for m, row in t["methods"].items()} for t in tables]
    assert tables[1] == tables[0] and tables[2] == tables[0], pool_warnings(*logs)
