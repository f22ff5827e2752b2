"""Loading finished run folders (as written by mapex.results) for the evaluation report.

A run folder holds metrics.json (AUCs, world, method, start), curves.csv (the sampled metric
curves) and optionally snapshots.npz (maps at a few steps). Unreadable folders are skipped
with a warning rather than failing the whole report, since a results folder may hold a few
broken or half-written runs. Every file is read within the limits of `mapex.io_limits`
(a regular file, at most `world.max_file_bytes`; snapshots judged by their headers first).
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapex.io_limits import check_npz, read_text
from mapex.results import (
    CURVES_FILE,
    METRICS_FILE,
    SNAPSHOTS_FILE,
    CampaignError,
    config_difference,
    folder_name,
    level_key,
    method_label,
    read_campaign,
)
from mapex.worlds.starts import start_label

METRICS = ("coverage", "iou", "tu")
METRIC_LABELS = {"coverage": "Coverage", "iou": "IoU", "tu": "TU"}

Warn = Callable[[str], None]


class ReportError(ValueError):
    """Input the report cannot be made from; the message names the cause."""


def warn_stderr(message: str) -> None:
    """Default warning sink: one line on stderr."""
    print(f"mapex.report: warning: {message}", file=sys.stderr)


@dataclass(frozen=True)
class RunRecord:
    """One finished run: its metrics.json and its curves (`tu` NaN where not sampled)."""

    path: Path
    metrics: dict
    steps: np.ndarray  # int64 sample steps
    coverage: np.ndarray
    iou: np.ndarray
    tu: np.ndarray

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def method(self) -> str:
        """The method as the report groups runs: its predictor when not the default
        (`mapex@oracle`, `mapex.results.method_label`) and a team's size (`mapex_team x2`)
        are part of it, so runs of two predictors, or teams of 2 and of 4, are compared,
        not pooled."""
        team = self.metrics.get("team")
        name = self.labelled_method
        return f"{name} x{team['robots']}" if team else name

    @property
    def labelled_method(self) -> str:
        """The method with its predictor, as in the run's folder name (`mapex@oracle`)."""
        predictor = self.metrics.get("predictor")
        return method_label(
            str(self.metrics["method"]), None if predictor is None else str(predictor)
        )

    @property
    def world(self) -> str:
        return str(self.metrics["world"])

    @property
    def start(self) -> str:
        """The run's start as in run names: `start2` (a corner) or `start-r15c380` (a cell)."""
        corner = self.metrics["start_index"]
        if corner is not None:
            return start_label(int(corner))
        return start_label(tuple(int(v) for v in self.metrics["start"]))

    @property
    def seed(self) -> int:
        return int(self.metrics.get("seed", 0))

    @property
    def early_termination(self) -> bool:
        return bool(self.metrics.get("early_termination", False))

    @property
    def end_reason(self) -> str | None:
        """`budget`, `explored` or `unreachable`; None for records older than the field."""
        return self.metrics.get("end_reason")

    @property
    def degraded(self) -> bool:
        """True when G was missing at some planning step or metric sample of the run."""
        return bool(self.metrics.get("degraded_steps")) or bool(
            self.metrics.get("degraded_metric_samples")
        )

    def auc(self, metric: str) -> float:
        """The run's AUC of `metric` (NaN when the run has none, e.g. no TU sample)."""
        value = self.metrics["auc"].get(metric)
        return float("nan") if value is None else float(value)

    def reach_levels(self) -> list[tuple[str, float]]:
        """The (metric, level) pairs whose first step the run recorded (none: older runs)."""
        reached = self.metrics.get("reached") or {}
        return [(metric, float(level)) for metric, levels in reached.items() for level in levels]

    def reached(self, metric: str, level: float) -> int | None:
        """The first step at which `metric` reached `level` (None: never in this run)."""
        step = (self.metrics.get("reached") or {}).get(metric, {}).get(level_key(level))
        return None if step is None else int(step)

    def curve(self, metric: str) -> np.ndarray:
        return {"coverage": self.coverage, "iou": self.iou, "tu": self.tu}[metric]


def load_runs(
    results_dir: Path,
    warn: Warn = warn_stderr,
    exclude: Iterable[Path] = (),
    skipped: list[str] | None = None,
) -> list[RunRecord]:
    """Every finished run folder of `results_dir`, sorted by name; hidden (staging) folders and
    `exclude` are ignored, unreadable folders skipped with one warning line each (and their
    names appended to `skipped`)."""
    excluded = {Path(p).resolve() for p in exclude}
    runs = []
    for folder in sorted(Path(results_dir).iterdir()):
        if not folder.is_dir() or folder.name.startswith(".") or folder.resolve() in excluded:
            continue
        try:
            runs.append(load_run(folder))
        except (OSError, ValueError, KeyError, TypeError) as error:
            warn(f"skipping {folder.name}: {error}")
            if skipped is not None:
                skipped.append(folder.name)
    return runs


# metrics.json fields in which two runs of one episode may differ and still agree: how long
# it took and which predictor workers answered (their ids name their processes)
CIRCUMSTANTIAL_FIELDS = ("wall_time_s", "member_workers")


def load_folders(
    results_dirs: Sequence[Path],
    warn: Warn = warn_stderr,
    exclude: Iterable[Path] = (),
    skipped: list[str] | None = None,
) -> list[RunRecord]:
    """The runs of several results folders (the shards of one experiment), merged: an
    episode found in more than one is kept once when its records agree (`same_episode`)
    and is a ReportError naming both places when they do not. Sorted by name."""
    runs: dict[str, RunRecord] = {}
    for results_dir in results_dirs:
        for run in load_runs(results_dir, warn, exclude, skipped):
            kept = runs.setdefault(run.name, run)
            differing = None if kept is run else record_difference(kept.metrics, run.metrics)
            if differing is not None:
                raise ReportError(
                    f"episode {run.name} is in {kept.path.parent} and in {run.path.parent} "
                    f"with different records ({differing}): keep one of them"
                )
    return [runs[name] for name in sorted(runs)]


def record_difference(first: dict, second: dict) -> str | None:
    """The first field in which two metrics.json records of one episode differ, leaving out
    `CIRCUMSTANTIAL_FIELDS` (e.g. `auc.iou (0.61, not 0.6)`), or None when they agree."""
    mine, theirs = (
        {key: value for key, value in record.items() if key not in CIRCUMSTANTIAL_FIELDS}
        for record in (first, second)
    )
    if mine == theirs:
        return None
    return config_difference(theirs, mine) or "the fields they hold"


def campaign_episodes(results_dirs: Sequence[Path]) -> list[str]:
    """Every episode the campaign.json of any of the folders lists (services.evaluate writes
    one; all shards of an experiment list all its episodes), in their order; ReportError
    (one line) for an unreadable one."""
    names: dict[str, None] = {}
    for results_dir in results_dirs:
        try:
            campaign = read_campaign(results_dir)
        except CampaignError as error:
            raise ReportError(str(error)) from None
        names.update(dict.fromkeys(campaign["episodes"] if campaign else ()))
    return list(names)


def missing_runs(runs: Iterable[RunRecord]) -> list[str]:
    """The runs a complete experiment would also hold: every method present, on every start
    and seed present for each world; their folder names, sorted."""
    runs = list(runs)
    methods = {r.method for r in runs}
    have = {(r.world, r.method, r.start, r.seed) for r in runs}
    cells = {(r.world, r.start, r.seed) for r in runs}
    wanted = {(w, m, s, seed) for (w, s, seed) in cells for m in methods}
    return sorted(_run_folder(*run) for run in wanted - have)


def _run_folder(world: str, method: str, start: str, seed: int) -> str:
    """The folder of a run of `method` as the report labels it: a team (`mapex_team x2`)
    is `<world>-mapex_team-<start>-seed<s>-team2` and a run of the oracle (`mapex@oracle`)
    `<world>-mapex@oracle-<start>-seed<s>`, as `mapex.results.episode_name` writes."""
    name, _, robots = method.partition(" x")
    folder = folder_name(world, name, start, seed)
    return f"{folder}-team{robots}" if robots else folder


def load_run(folder: Path) -> RunRecord:
    """One run folder (ReportError / OSError / ValueError when it is incomplete or corrupt)."""
    metrics_path = folder / METRICS_FILE
    if not metrics_path.exists():
        raise ReportError(f"no {METRICS_FILE}")
    try:
        metrics = json.loads(read_text(metrics_path))
    except RecursionError:
        raise ReportError(f"{METRICS_FILE} is nested too deeply") from None
    if not isinstance(metrics, dict):
        raise ReportError(f"{METRICS_FILE} is not an object")
    missing = [k for k in ("world", "method", "start_index", "auc") if k not in metrics]
    if missing:
        raise ReportError(f"{METRICS_FILE} lacks {', '.join(missing)}")
    steps, coverage, iou, tu = _read_curves(folder / CURVES_FILE)
    return RunRecord(folder, metrics, steps, coverage, iou, tu)


def _read_curves(path: Path) -> tuple[np.ndarray, ...]:
    reader = csv.DictReader(io.StringIO(read_text(path), newline=""))
    rows = list(reader)
    if rows and not set(("step", *METRICS)) <= set(rows[0]):
        raise ReportError(f"{path.name} lacks one of the columns step, {', '.join(METRICS)}")
    columns = len(reader.fieldnames or ())
    for number, row in enumerate(rows, start=2):
        if None in row or None in row.values():  # more, or fewer, fields than the header
            raise ReportError(f"{path.name}: line {number} does not have {columns} fields")
    steps = np.array([int(row["step"]) for row in rows], dtype=np.int64)
    values = [
        np.array([float(row[m]) if row[m] else math.nan for row in rows], dtype=np.float64)
        for m in METRICS
    ]
    return (steps, *values)


@dataclass(frozen=True)
class Snapshots:
    """Maps kept at a few steps: observed codes and G's map (uint8 q / 255, may be absent)."""

    steps: np.ndarray
    observed: np.ndarray
    prediction: np.ndarray | None

    def at(self, step: int) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(observed, prediction) at `step`, or None when the run has no snapshot there."""
        where = np.flatnonzero(self.steps == step)
        if where.size == 0:
            return None
        i = int(where[0])
        return self.observed[i], None if self.prediction is None else self.prediction[i]


def has_snapshots(run: RunRecord) -> bool:
    """True when the run folder holds a snapshots.npz."""
    return (run.path / SNAPSHOTS_FILE).is_file()


def load_snapshots(run: RunRecord) -> Snapshots | None:
    """The run's snapshots.npz, or None when it has none (older runs)."""
    path = run.path / SNAPSHOTS_FILE
    if not path.exists():
        return None
    check_npz(path, what="snapshots")
    with np.load(path, allow_pickle=False) as data:
        prediction = data["prediction"] if "prediction" in data.files else None
        return Snapshots(data["steps"], data["observed"], prediction)


def load_snapshots_or_warn(run: RunRecord, warn: Warn = warn_stderr) -> Snapshots | None:
    """The run's snapshots, or None with one warning when its snapshots.npz is unreadable
    (the figure then shows that run's panels as missing instead of failing the report)."""
    try:
        return load_snapshots(run)
    except (OSError, ValueError, KeyError) as error:
        warn(f"{run.name}: unreadable {SNAPSHOTS_FILE} ({error})")
        return None
