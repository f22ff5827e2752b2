"""An experiment run whole and in shards (`services.evaluate --shard K/N`), each shard a
process of its own: the commands (so that a test can run them anywhere, e.g. each in a
network namespace of its own), running them, and what two runs of an episode must agree on."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from service_processes import REPO_ROOT

# 2 quick methods (nearest plans without the predictor, ig_hector from its map) x 1 small
# generated world x 2 starts; by step 60 the two methods' runs differ
CAMPAIGN = ("--maps", "generated:0", "--methods", "nearest,ig_hector", "--starts", "0,1",
            "--steps", "60")  # fmt: skip
RUN_DEADLINE_S = 600.0  # a whole run on a loaded 2-core machine takes well under a minute


def evaluate_command(out: Path, *extra: str, campaign: Sequence[str] = CAMPAIGN) -> list[str]:
    """`python -m services.evaluate` of `campaign` into `out`, without a progress bar."""
    return [sys.executable, "-m", *evaluate_case(out, *extra, campaign=campaign)]


def evaluate_case(out: Path, *extra: str, campaign: Sequence[str] = CAMPAIGN) -> list[str]:
    """`evaluate_command` as a case of commands_at_once.run_python_m (no interpreter)."""
    return ["services.evaluate", *campaign, "--out", str(out), "--no-progress", *extra]


def shard_commands(
    out: Path | Sequence[Path], count: int, *extra: str, campaign: Sequence[str] = CAMPAIGN
) -> list[list[str]]:
    """The commands of shards 0..count-1: all into the folder `out`, or shard K into `out[K]`."""
    outs = [out] * count if isinstance(out, Path) else list(out)
    assert len(outs) == count, "one folder per shard, or one for all"
    return [
        evaluate_command(outs[k], "--shard", f"{k}/{count}", *extra, campaign=campaign)
        for k in range(count)
    ]


def run_commands(
    commands: Sequence[Sequence[str]], log_dir: Path, name: str, at_once: bool = True
) -> list[int]:
    """Run `commands` (all at once, or one after another), each logging to
    `log_dir/<name>-<k>.log`; their exit codes. None is left running."""
    processes: list[subprocess.Popen] = []
    codes: list[int] = []
    try:
        for k, command in enumerate(commands):
            with open(log_dir / f"{name}-{k}.log", "wb") as log:
                processes.append(
                    subprocess.Popen(command, cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT)
                )
            if not at_once:
                codes.append(processes[-1].wait(RUN_DEADLINE_S))
        return codes if not at_once else [p.wait(RUN_DEADLINE_S) for p in processes]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.wait()


def run_records(out: Path) -> dict:
    """Each published run's metrics.json, by folder name (hidden folders are being written)."""
    found = sorted(out.glob("*/metrics.json"))
    return {m.parent.name: json.loads(m.read_text()) for m in found if m.parent.name[0] != "."}


def reproduced_part(record: dict, other: dict) -> tuple:
    """What a rerun must reproduce of a run recorded as `record` and, in the other
    evaluation, as `other`.

    All of it (AUCs, trajectory length, re-plans) when the pool served both in time. When a
    member did not answer in time in either, that run is degraded (DESIGN.md) and its
    timing-dependent part is left out: after a missed metric sample its IoU and TU, after a
    missed re-plan everything but its length.
    """
    if record["degraded_steps"] or other["degraded_steps"]:
        return (record["steps"],)
    auc, reached = dict(record["auc"]), dict(record["reached"])
    if record["degraded_metric_samples"] or other["degraded_metric_samples"]:
        auc, reached = {"coverage": auc["coverage"]}, {"coverage": reached["coverage"]}
    return auc, reached, record["steps"], record["replans"]


def comparable_tables(first: dict, second: dict) -> tuple[dict, dict]:
    """The two evaluations' runs, each reduced to what both must agree on."""

    def reduce(table: dict, other: dict) -> dict:
        return {
            name: reproduced_part(record, other[name]) if name in other else record
            for name, record in table.items()
        }

    return reduce(first, second), reduce(second, first)


def any_degraded(*tables: dict) -> bool:
    """Whether a member failed to answer in time in any run of the tables."""
    return any(
        record["degraded_steps"] or record["degraded_metric_samples"]
        for table in tables
        for record in table.values()
    )


def pool_warnings(*logs: Path) -> str:
    """The warnings of the evaluations' logs: why a member did not answer, if one did not."""
    lines = (line for log in logs for line in log.read_text(errors="replace").splitlines())
    return "\n".join(line for line in lines if " WARNING " in line)
