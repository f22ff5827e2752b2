"""The results folder of a run: metrics JSON, curves CSV, trajectory CSV, snapshots and a PNG.

snapshots.npz holds, at the steps of `MetricsConfig.snapshot_steps` the run reached,
`steps` int64 (n,), `observed` uint8 (n, rows, cols) codes of O_t and, when a predictor
judged the map, `prediction` uint8 (n, rows, cols): G's whole-map map, q / 255.

A folder is written under a temporary name and renamed into place, so a reader
(or a resumed batch evaluation) never sees half a run. An experiment's folder
(`services.evaluate`) also holds campaign.json, its episodes and settings (`claim_campaign`),
which its shards check and `mapex.report` lists missing episodes from.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import math
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from mapex.episode import COVERAGE_REACHED, IOU_REACHED, EpisodeResult
from mapex.grid import quantise_probability
from mapex.io_limits import read_text
from mapex.methods import records_team
from mapex.metrics import idle_steps
from mapex.plotting import plot_episode
from mapex.prediction import DEFAULT_PREDICTOR
from mapex.worlds.base import World
from mapex.worlds.starts import StartSpec, start_label

METRICS_FILE = "metrics.json"
CURVES_FILE = "curves.csv"
TRAJECTORY_FILE = "trajectory.csv"  # robot 0's for a team
TEAM_TRAJECTORIES_FILE = "trajectories.csv"  # every robot's, for a team
PICTURE_FILE = "final.png"
SNAPSHOTS_FILE = "snapshots.npz"
DEFAULT_RESULTS_DIR = Path("results")  # where a run goes without --out


class OutputError(OSError):
    """Results cannot be written where asked: one line, naming the folder and the reason
    (an OSError, so every command's one-line error handling already reports it)."""


def check_output_folder(folder: Path) -> Path:
    """Create `folder` and write and remove a probe file in it, so that a bad output place
    (a file, no permission, a full disk) is found before any work, not after the run."""
    folder = _not_a_file(Path(folder))
    try:
        folder.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(prefix=".probe-", dir=folder)  # unique: shards share it
        with os.fdopen(handle, "wb") as written:
            written.write(b"mapex")
        os.unlink(probe)
    except OSError as error:
        raise OutputError(f"cannot write results to {folder}: {_reason(error)}") from None
    return folder


RUN_FILES = frozenset(
    {METRICS_FILE, CURVES_FILE, TRAJECTORY_FILE, TEAM_TRAJECTORIES_FILE, PICTURE_FILE,
     SNAPSHOTS_FILE}
)  # fmt: skip  # what a run folder holds: all a new run may replace


def check_run_folder(out_dir: Path) -> Path:
    """A run folder can be written to `out_dir`: it is new, empty, or an older run's folder
    (which the run replaces). A folder holding anything else is refused (one line): a run
    never deletes what it did not write."""
    out_dir = _not_a_file(Path(out_dir))
    if out_dir.is_dir():
        foreign = sorted(entry.name for entry in out_dir.iterdir() if entry.name not in RUN_FILES)
        if foreign:
            shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
            raise OutputError(
                f"--out {out_dir} holds what is not a run's folder ({shown}): a run replaces "
                f"only an older run's folder; give a new or empty folder"
            )
    check_output_folder(out_dir.parent)
    return out_dir


def check_destination(out: Path | None) -> None:
    """Before any work: a run's folder can go to `out`, or (None) under DEFAULT_RESULTS_DIR."""
    check_run_folder(out) if out else check_output_folder(DEFAULT_RESULTS_DIR)


def destination(out: Path | None, result: EpisodeResult) -> Path:
    """Where the run's folder goes: `out`, or DEFAULT_RESULTS_DIR / its run name."""
    return out or DEFAULT_RESULTS_DIR / run_name(result)


def _not_a_file(path: Path) -> Path:
    if path.exists() and not path.is_dir():
        raise OutputError(f"cannot write results to {path}: it is a file")
    return path


def run_name(result: EpisodeResult) -> str:
    """A file-system-safe name for the run, e.g. `generated_0-mapex-start0-seed0`
    (`...-seed0-team2` for a team of two, `generated_0-mapex@oracle-...` under the oracle)."""
    return episode_name(
        result.world, result.method, result.start_spec, result.seed, result.robots,
        result.predictor,
    )  # fmt: skip


# what a run's record says of the default predictor: `lama`, or `zenoh` (the name the
# distributed ensemble recorded before it named the predictor its workers serve)
DEFAULT_PREDICTOR_RECORDS = (DEFAULT_PREDICTOR, "zenoh")


def method_label(method: str, predictor: str | None) -> str:
    """The method as results folders and the report name it: `mapex`, or `mapex@oracle` for
    a run of another predictor than the default. A method that reads no prediction
    (`observed_map`, ...) is labelled too: it explores the same under every predictor, but
    its IoU and TU are G's map of what it saw, so they are the predictor's. A run of no
    predictor or of the default (`DEFAULT_PREDICTOR_RECORDS`) is not labelled, so folders and
    reports from before predictors were chosen keep their names."""
    if predictor is None or predictor in DEFAULT_PREDICTOR_RECORDS:
        return method
    return f"{method}@{predictor}"


def episode_name(
    world: str,
    method: str,
    start: StartSpec,
    seed: int,
    robots: int = 1,
    predictor: str | None = None,
) -> str:
    """The results-folder name of a run: `<world>-<method label>-<start label>-seed<s>`, with
    the world name made file-system safe (e.g. `50052748-mapex-start-r15c380-seed0`), the
    predictor in the label when it is not the default (`method_label`: `mapex@oracle`), and
    `-team<N>` for a team's record (`mapex.methods.records_team`)."""
    name = folder_name(world, method_label(method, predictor), start_label(start), seed)
    return f"{name}-team{robots}" if records_team(method, robots) else name


def folder_name(world: str, method: str, start: str, seed: int) -> str:
    """`episode_name` from a method label (`mapex@oracle`) and a start label (`start2`,
    `start-r15c380`)."""
    safe_world = world.replace(":", "_").replace("/", "_")
    return f"{safe_world}-{method}-{start}-seed{seed}"


def describe_end(result: EpisodeResult) -> str:
    """How the run ended, for a summary line: `ran all 1000 steps`, `no frontier left at
    step 812` or `no frontier reachable at step 37`."""
    if result.finished_at is None:
        return f"ran all {result.steps} steps"
    why = {
        "explored": "no frontier left",
        "unreachable": "no frontier reachable",
        IOU_REACHED: f"G's IoU reached {result.config.until_iou}",
        COVERAGE_REACHED: f"coverage reached {result.config.metrics.until_coverage}",
    }
    return f"{why[result.end_reason]} at step {result.finished_at}"


def summary(result: EpisodeResult) -> dict:
    """The run's record as plain JSON-serialisable data."""
    return {
        "world": result.world,
        "method": result.method,
        "predictor": result.predictor,
        "start_index": result.start_index,
        "start": list(result.start),
        "seed": result.seed,
        "steps": result.steps,
        "finished_at": result.finished_at,
        "early_termination": result.finished_at is not None,
        "end_reason": result.end_reason,
        "auc": _json_floats(result.curves.auc()),
        "reached": reached_record(result.curves.reached),
        "final": {
            "coverage": result.curves.coverage[-1],
            "iou": result.curves.iou[-1],
            "tu": _json_float(result.curves.tu[-1]),
        },
        # every robot's path, in metres, summed (the team's), and each robot's steps
        # standing still while the run went on
        "path_length_m": round(sum(result.path_lengths_m), 2),
        "idle_steps": [idle_steps(path) for path in result.trajectories],
        "replans": result.stats.replans,
        "approach_goals": result.stats.approach_goals,
        "path_repairs": result.stats.path_repairs,
        "degraded_steps": result.stats.degraded_steps,
        "fallback_steps": result.stats.fallback_steps,
        "degraded_metric_samples": result.degraded_samples,
        "degraded_from_start": result.degraded_from_start,
        "member_workers": {  # who answered each member query (remote predictor workers)
            "replans": [[t, served] for t, served in result.stats.member_workers],
            "metric_samples": [[t, served] for t, served in result.metric_workers],
        },
        **_team_summary(result),
        "wall_time_s": round(result.wall_time_s, 3),
        "config": dataclasses.asdict(result.config),
    }


def reached_record(reached: dict[str, dict[float, int | None]]) -> dict:
    """{metric: {"0.9": step or None}}: the first step each level was reached (None: never
    within the run, a censored run)."""
    return {
        metric: {level_key(level): step for level, step in levels.items()}
        for metric, levels in reached.items()
    }


def level_key(level: float) -> str:
    """A level as a metrics.json key: 0.9 -> "0.9", 0.95 -> "0.95"."""
    return f"{level:g}"


def _team_summary(result: EpisodeResult) -> dict:
    """The team fields of a team run's record (none for a single robot)."""
    if not result.is_team:
        return {}
    return {
        "team": {
            "robots": len(result.trajectories),
            "starts": [[int(v) for v in path[0]] for path in result.trajectories],
            "path_length_m": [round(length, 2) for length in result.path_lengths_m],
            "overlap": round(result.overlap, 4),
            "replans": [stats.replans for stats in result.robot_stats],
            "degraded_steps": [stats.degraded_steps for stats in result.robot_stats],
            "lost_at": {f"r{robot}": t for robot, t in sorted(result.lost_at.items())},
        }
    }


def write_results(result: EpisodeResult, world: World, out_dir: Path) -> Path:
    """Write the run's folder atomically to `out_dir` (replacing an older one); on any
    failure nothing is left behind and OutputError says why in one line."""
    out_dir = check_run_folder(out_dir)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        _write_run_files(result, world, staging)
        return move_into_place(staging, out_dir)
    except OSError as error:
        shutil.rmtree(staging, ignore_errors=True)
        raise OutputError(f"could not write the run to {out_dir}: {_reason(error)}") from None


def _write_run_files(result: EpisodeResult, world: World, staging: Path) -> None:
    (staging / METRICS_FILE).write_text(json.dumps(summary(result), indent=2) + "\n")
    _write_curves(result, staging / CURVES_FILE)
    _write_trajectory(result, staging / TRAJECTORY_FILE)
    _write_snapshots(result, staging / SNAPSHOTS_FILE)
    plot_episode(
        staging / PICTURE_FILE,
        f"{result.world} | {method_label(result.method, result.predictor)} | "
        f"{start_label(result.start_spec)} | seed {result.seed}",
        result.final_observed,
        result.final_prediction,
        world.occupancy,
        result.trajectories,
    )
    if result.is_team:
        _write_team_trajectories(result, staging / TEAM_TRAJECTORIES_FILE)


@contextlib.contextmanager
def staged_file(path: Path) -> Iterator[Path]:
    """A hidden temporary name beside `path` (same suffix, so writers that go by it still
    work), renamed onto `path` when the block ends well and removed when it raises: a
    reader sees the old file or the whole new one, never half of one."""
    partial = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield partial
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def move_into_place(folder: Path, out_dir: Path) -> Path:
    """Rename a whole written `folder` to `out_dir`, replacing an older one; `out_dir`."""
    if out_dir.exists():
        shutil.rmtree(out_dir)
    folder.rename(out_dir)
    return out_dir


# ---------------------------------------------------------------- an experiment's campaign

CAMPAIGN_FILE = "campaign.json"  # an experiment's episodes and settings, in its results folder


class CampaignError(ValueError):
    """A results folder's campaign.json cannot be read or belongs to another campaign
    (one line)."""


def campaign_record(episodes: Mapping[str, int], config: dict, shards: int = 1) -> dict:
    """What campaign.json holds: every episode of the experiment, all shards' (its results
    folder name -> its step budget, in the canonical order that shards are dealt from),
    the plain exploration configuration they share (without `steps`, which is per episode)
    and the number of shards it is split into (1: not sharded)."""
    shared = {key: value for key, value in config.items() if key != "steps"}
    return {"episodes": dict(episodes), "config": shared, "shards": shards}


def read_campaign(folder: Path) -> dict | None:
    """The campaign.json of `folder`, or None when it has none; CampaignError (one line)
    when it is unreadable or no campaign record."""
    path = Path(folder) / CAMPAIGN_FILE
    if not path.exists():
        return None
    try:
        record = json.loads(read_text(path))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError, OSError) as error:
        raise CampaignError(f"{path}: unreadable ({' '.join(str(error).split())})") from None
    episodes = record.get("episodes") if isinstance(record, dict) else None
    if not (isinstance(episodes, dict) and isinstance(record.get("shards"), int)):
        raise CampaignError(f"{path}: not a campaign record (episodes and shards)")
    return record


def campaign_difference(written: dict, mine: dict) -> str | None:
    """How the campaign record `written` differs from `mine` (one phrase), or None: the
    shard count, the episodes (names, budgets and order, from which the shards are dealt)
    and the configuration (`config_difference`, fields both have)."""
    if written.get("shards") != mine["shards"]:
        return f"it is split into {written.get('shards')} shard(s), not {mine['shards']}"
    theirs, ours = written["episodes"], mine["episodes"]
    for name, steps in ours.items():
        if name not in theirs:
            return f"it has no episode {name}"
        if theirs[name] != steps:
            return f"it runs {name} for {theirs[name]} steps, not {steps}"
    extra = [name for name in theirs if name not in ours]
    if extra:
        return f"it also has episode {extra[0]}"
    if list(theirs) != list(ours):
        return "it lists the episodes in another order (--maps, --methods, --starts, --seeds)"
    differing = config_difference(written.get("config"), mine["config"])
    return None if differing is None else f"it runs with another {differing}"


def claim_campaign(folder: Path, record: dict) -> None:
    """Write `record` (`campaign_record`) as `folder`/campaign.json, or check it against the
    one there. The file appears whole and only once (a hard link of a written file, where the
    file system has them), so of several shards starting at once one writes it and the
    others compare. An unreadable one is a CampaignError, and so is a different one when
    either is split into shards (shards of two campaigns would run the same episodes into one
    place); an unsharded run replaces an unsharded one (it resumes a changed experiment:
    services.evaluate runs again each episode that differs)."""
    path = Path(folder) / CAMPAIGN_FILE
    written = path.with_name(f".{CAMPAIGN_FILE}.{os.getpid()}.{uuid.uuid4().hex}")  # unique
    try:
        with written.open("x") as partial:  # as readable as the runs (mkstemp's are private)
            partial.write(json.dumps(record, indent=1) + "\n")
        if _create_once(written, path):
            return
        try:
            theirs = read_campaign(folder)
        except CampaignError as error:
            raise CampaignError(f"{error}: delete it once no evaluation writes there") from None
        problem = None if theirs is None else campaign_difference(theirs, record)
        if problem is None:
            return
        if record["shards"] > 1 or theirs["shards"] > 1:
            raise CampaignError(
                f"{path} is another campaign's ({problem}): give this one another --out, or "
                f"delete that file once none of its shards runs"
            )
        os.replace(written, path)
    finally:
        written.unlink(missing_ok=True)


def _create_once(written: Path, path: Path) -> bool:
    """Give `written`'s content the name `path` unless that exists; whether it did."""
    try:
        os.link(written, path)
        return True
    except FileExistsError:
        return False
    except OSError:  # no hard links here (some network file systems): create exclusively
        try:
            with path.open("x") as handle:
                handle.write(written.read_text())
            return True
        except FileExistsError:
            return False


def config_difference(written: object, expected: dict | None, prefix: str = "") -> str | None:
    """The first dotted field (e.g. `path_gain.top_k`) whose value differs between two plain
    configurations, looking only at fields both have (so a field added later does not count)."""
    if expected is None or not isinstance(written, dict):
        return None if expected is None else "configuration (none recorded)"
    for key in sorted(expected.keys() & written.keys()):
        mine, theirs = expected[key], written[key]
        if isinstance(mine, dict):
            found = config_difference(theirs, mine, f"{prefix}{key}.")
            if found is not None:
                return found
        elif mine != theirs:
            return f"{prefix}{key} ({theirs!r}, not {mine!r})"
    return None


def _write_curves(result: EpisodeResult, path: Path) -> None:
    curves = result.curves
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["step", "coverage", "iou", "tu"])
        for row in zip(curves.steps, curves.coverage, curves.iou, curves.tu, strict=True):
            writer.writerow([row[0], *(f"{v:.6f}" if math.isfinite(v) else "" for v in row[1:])])


def _write_team_trajectories(result: EpisodeResult, path: Path) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["step", "robot", "row", "col"])
        for robot, trajectory in enumerate(result.trajectories):
            writer.writerows([t, robot, int(r), int(c)] for t, (r, c) in enumerate(trajectory))


def _write_trajectory(result: EpisodeResult, path: Path) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["step", "row", "col"])
        writer.writerows([t, int(r), int(c)] for t, (r, c) in enumerate(result.trajectory))


def _write_snapshots(result: EpisodeResult, path: Path) -> None:
    steps = sorted(result.snapshots)
    arrays = {
        "steps": np.asarray(steps, dtype=np.int64),
        "observed": np.asarray([result.snapshots[t][0] for t in steps], dtype=np.uint8),
    }
    if steps and all(result.snapshots[t][1] is not None for t in steps):
        arrays["prediction"] = np.asarray(
            [quantise_probability(result.snapshots[t][1]) for t in steps], dtype=np.uint8
        )
    np.savez_compressed(path, **arrays)


def _reason(error: OSError) -> str:
    return error.strerror or str(error)


def _json_float(value: float) -> float | None:
    return None if not math.isfinite(value) else round(float(value), 6)


def _json_floats(values: dict[str, float]) -> dict[str, float | None]:
    return {key: _json_float(value) for key, value in values.items()}
