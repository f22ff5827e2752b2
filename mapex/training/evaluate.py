"""`python -m mapex.training.evaluate`: how good are the predictions, on their own?

On validation worlds never trained on (the six validation maps, 2 KTH floors and 4 IPA
buildings, or with `--kth` the 18 KTH validation floors: the two official ones and the 16
held-out kth_sdf floors), observed maps are taken from nearest-frontier runs at t = 100,
300, 600 from all 4 starts, and the
occupied-class IoU over the *unknown* cells inside the building footprint is measured for
G, a reference G (by default the v2 weights), the classical predictor
and "unknown = free"; the ensemble variance is scored as a detector of G's wrong cells
(AUROC). Four tables: per map, per map and time, near / far from the known map, and
against a local predictor's ceiling; what they say is in docs/prediction.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import rankdata
from tqdm import tqdm

from mapex.config import ExplorationConfig
from mapex.exit_codes import EXIT_USAGE
from mapex.grid import RESOLUTION_M, UNKNOWN, observed_to_probability
from mapex.metrics import building_footprint, occupied_iou
from mapex.plotting import occupancy_image, plt
from mapex.prediction import make_predictor
from mapex.prediction.base import EnsemblePrediction
from mapex.prediction.classical import distance_to_known
from mapex.prediction.config import (
    DEFAULT_INFERENCE,
    InferenceConfig,
    PredictorEvaluationConfig,
    add_inference_arguments,
    inference_from_args,
)
from mapex.prediction.weights import WEIGHTS_DIR, WeightsError
from mapex.training.dataset import snapshots_at
from mapex.worlds import WorldError, load_world, start_poses
from mapex.worlds.base import World
from mapex.worlds.data import kth_validation_specs, validation_map_dirs

REFERENCE_WEIGHTS_DIR = WEIGHTS_DIR / "v2"  # the ensemble shipped before predictor v3


@dataclass
class CellScores:
    """Scores over one set of cells: IoUs and the variance-vs-error AUROC."""

    iou_g: float
    iou_classical: float
    iou_unknown_free: float
    auroc: float
    iou_reference: float = float("nan")  # the reference G's (nan without one)


@dataclass
class SnapshotScore:
    """Scores of one snapshot over all unknown footprint cells, and near / far from the
    known map."""

    world: str
    start: int
    t: int
    all: CellScores
    near: CellScores
    far: CellScores
    local_ceiling: float  # IoU of the perfect near-only predictor (local_ceiling_iou)
    g_inside_only: float  # G's IoU with its walls outside the building taken away
    far_variance_share: float  # of the map's total variance, in unknown cells > far_cells away


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve of `scores` for boolean `labels` (ties count half)."""
    positives = int(labels.sum())
    negatives = labels.size - positives
    if positives == 0 or negatives == 0:
        return float("nan")
    ranks = rankdata(scores)
    return float((ranks[labels].sum() - positives * (positives + 1) / 2) / (positives * negatives))


def score_cells(
    truth: np.ndarray,
    cells: np.ndarray,
    learned: EnsemblePrediction,
    classical_main: np.ndarray,
    threshold: float,
    reference_main: np.ndarray | None = None,
) -> CellScores:
    """IoU of G, of classical, of unknown = free and of a reference G (if given), and the
    AUROC, over `cells` (bool); all NaN when `cells` is empty (a snapshot with no unknown
    cell that far from the known map has no score there, rather than a perfect one)."""
    if not cells.any():
        return CellScores(*(float("nan"),) * 5)
    wrong = (learned.main >= threshold) != truth
    reference = (
        float("nan")
        if reference_main is None
        else occupied_iou(reference_main >= threshold, truth, cells)
    )
    return CellScores(
        occupied_iou(learned.main >= threshold, truth, cells),
        occupied_iou(classical_main >= threshold, truth, cells),
        occupied_iou(np.zeros_like(truth), truth, cells),
        auroc(learned.variance[cells], wrong[cells]),
        reference,
    )


def far_variance_share(variance: np.ndarray, observed: np.ndarray, far_cells: int) -> float:
    """Share of the map's total ensemble variance that lies in unknown cells more than
    `far_cells` from any known cell (nan when the variance is zero everywhere)."""
    total = float(variance.sum(dtype=np.float64))
    if total <= 0:
        return float("nan")
    far = ~near_known(observed, far_cells)
    return float(variance[far].sum(dtype=np.float64)) / total


def near_known(observed: np.ndarray, within_cells: int) -> np.ndarray:
    """Cells (bool) at most `within_cells` (Euclidean) from a known cell."""
    return distance_to_known(observed == UNKNOWN) <= within_cells


def local_ceiling_iou(truth: np.ndarray, cells: np.ndarray, near: np.ndarray) -> float:
    """Occupied IoU over `cells` of a perfect predictor that paints walls only in `near`
    (the ground truth there, free beyond): what a predictor that only continues the walls
    it sees could reach at best."""
    return occupied_iou(truth & near, truth, cells)


def outside_building(world: World) -> np.ndarray:
    """Free cells (bool) outside the building's valid space: beyond its outer walls."""
    return ~world.valid_space & ~world.occupancy


def evaluate(
    map_specs: list[str],
    settings: PredictorEvaluationConfig,
    figure: Path | None,
    weights_dir: Path = WEIGHTS_DIR,
    inference: InferenceConfig = DEFAULT_INFERENCE,
    reference_dir: Path | None = REFERENCE_WEIGHTS_DIR,
) -> list[SnapshotScore]:
    """Score every (map, start, time) snapshot of the ensemble in `weights_dir` (and the G of
    `reference_dir`, if given), run as `inference` says; optionally draw one of them."""
    options = inference.ensemble_options()
    learned = make_predictor("lama", weights_dir=weights_dir, **options)
    reference = (
        None
        if reference_dir is None
        else make_predictor("lama", weights_dir=reference_dir, **options)
    )
    classical = make_predictor("classical")
    config = ExplorationConfig()
    threshold = config.metrics.prediction_threshold
    times = settings.snapshot_times
    drawn = (map_specs[-1], 0, times[len(times) // 2])  # which snapshot the figure shows
    worlds = {spec: load_world(spec) for spec in map_specs}  # fail before any work
    scores = []
    jobs = [(spec, s) for spec in map_specs for s in range(4)]
    for map_spec, start_index in tqdm(jobs, desc="exploring", unit="run"):
        world = worlds[map_spec]
        footprint = building_footprint(world.valid_space, config.metrics.footprint_margin_cells)
        start = start_poses(world, config.world.start_clearance_cells)[start_index]
        snapshots, _ = snapshots_at(world, "nearest", start, list(times))
        for t in times:
            observed = snapshots[t]
            prediction = learned.predict(observed)
            classical_main = classical.predict_main(observed)
            reference_main = None if reference is None else reference.predict_main(observed)
            cells = (observed == UNKNOWN) & footprint
            near = near_known(observed, settings.near_known_cells)
            split = [cells, cells & near, cells & ~near]
            values = [
                score_cells(
                    world.occupancy, part, prediction, classical_main, threshold, reference_main
                )
                for part in split
            ]
            ceiling = local_ceiling_iou(world.occupancy, cells, near)
            walls_g = (prediction.main >= threshold) & ~outside_building(world)
            inside_only = occupied_iou(walls_g, world.occupancy, cells)
            far_share = far_variance_share(prediction.variance, observed, settings.far_cells)
            scores.append(
                SnapshotScore(world.name, start_index, t, *values, ceiling, inside_only, far_share)
            )
            if figure is not None and (map_spec, start_index, t) == drawn:
                draw_prediction(figure, world, observed, prediction, t)
    return scores


def draw_prediction(path: Path, world, observed, prediction: EnsemblePrediction, t: int) -> None:
    """Observed / predicted (G) / variance / ground truth, one above the other."""

    panels = [
        (f"observed map at t = {t}", occupancy_image(observed_to_probability(observed)), "gray"),
        ("prediction of G (wall probability)", occupancy_image(prediction.main), "gray"),
        ("ensemble variance", prediction.variance, "magma"),
        ("ground truth", occupancy_image(world.occupancy.astype(np.float32)), "gray"),
    ]
    rows, cols = observed.shape
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, len(panels) * 9 * rows / cols + 1))
    for ax, (title, image, cmap) in zip(axes, panels, strict=True):
        ax.imshow(image, cmap=cmap, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{world.name}, nearest-frontier run from start 0", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_map_table(scores: list[SnapshotScore], settings: PredictorEvaluationConfig) -> str:
    """Markdown table per map (means over its starts and times), then over every map: G's
    IoU against the reference G's, classical and unknown = free; the AUROC; the far share."""
    metres = settings.far_cells * RESOLUTION_M
    lines = [
        "| map | IoU G | IoU reference G | IoU classical | IoU unknown=free | G - reference "
        f"| AUROC var vs error | variance > {metres:g} m from known |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for world, group in _map_groups(scores):
        g, c, free, area = _means([s.all for s in group])
        reference = float(_nanmean([s.all.iou_reference for s in group]))
        far = float(_nanmean([s.far_variance_share for s in group]))
        versus = "-" if np.isnan(reference) else f"{g - reference:+.3f}"
        lines.append(
            f"| {world} | {g:.3f} | {_figure(reference)} | {c:.3f} | {free:.3f} | {versus} "
            f"| {area:.3f} | {_figure(far)} |"
        )
    return "\n".join(lines)


def _nanmean(values) -> float:
    """The mean of the values that are not NaN (NaN, without a warning, when none is)."""
    array = np.asarray(list(values), dtype=np.float64)
    kept = array[~np.isnan(array)]
    return float(kept.mean()) if kept.size else float("nan")


def _figure(value: float) -> str:
    """A table cell: three decimals, or "-" for a figure that does not exist (nan)."""
    return "-" if np.isnan(value) else f"{value:.3f}"


def _map_groups(scores: list[SnapshotScore]) -> list[tuple[str, list[SnapshotScore]]]:
    """Scores by map in order, then ("all", every score)."""
    groups: dict[str, list[SnapshotScore]] = {}
    for score in scores:
        groups.setdefault(score.world, []).append(score)
    return [*groups.items(), ("all", scores)]


def format_summary(scores: list[SnapshotScore], settings: PredictorEvaluationConfig) -> str:
    """Markdown table of the headline figures over every snapshot: G's and the reference G's
    IoU over all unknown cells, near and far from the known map, the best local predictor's
    IoU (G's margin over it), and the AUROC of the variance as a detector of G's errors."""
    metres = settings.near_known_cells * RESOLUTION_M

    mean = _nanmean

    g = [mean(getattr(s, part).iou_g for s in scores) for part in ("all", "near", "far")]
    ref = [mean(getattr(s, part).iou_reference for s in scores) for part in ("all", "near", "far")]
    ceiling = mean(s.local_ceiling for s in scores)
    auroc = mean(s.all.auroc for s in scores)
    lines = [
        f"| over {len(scores)} snapshots | all unknown | within {metres:g} m of known "
        f"| beyond {metres:g} m |",
        "|---|---|---|---|",
        f"| IoU G | {g[0]:.3f} | {g[1]:.3f} | {g[2]:.3f} |",
        f"| IoU reference G | {_figure(ref[0])} | {_figure(ref[1])} | {_figure(ref[2])} |",
        f"| G - reference | {g[0] - ref[0]:+.3f} | {g[1] - ref[1]:+.3f} | {g[2] - ref[2]:+.3f} |",
        f"| IoU best local predictor | {ceiling:.3f} | | |",
        f"| G - best local | {g[0] - ceiling:+.3f} | | |",
        f"| AUROC variance vs G's errors | {auroc:.3f} | | |",
    ]
    return "\n".join(lines)


def format_table(scores: list[SnapshotScore]) -> str:
    """Markdown table: per map and time, means over the 4 starts, then the overall mean."""
    lines = [
        "| map | t | IoU G | IoU classical | IoU unknown=free | G - classical "
        "| AUROC var vs error |",
        "|---|---|---|---|---|---|---|",
    ]
    for (world, t), group in _groups(scores):
        g, c, free, area = _means([s.all for s in group])
        lines.append(
            f"| {world} | {t} | {g:.3f} | {c:.3f} | {free:.3f} | {g - c:+.3f} | {area:.3f} |"
        )
    return "\n".join(lines)


def format_split_table(scores: list[SnapshotScore], near_known_cells: int) -> str:
    """Markdown table: G's and classical IoU and the AUROC near / far from the known map."""
    metres = near_known_cells * RESOLUTION_M
    lines = [
        f"Near (within {metres:g} m of a known cell) / far from the known map:",
        "",
        "| map | t | IoU G near / far | IoU classical near / far | AUROC near / far |",
        "|---|---|---|---|---|",
    ]
    for (world, t), group in _groups(scores):
        g_near, c_near, _, a_near = _means([s.near for s in group])
        g_far, c_far, _, a_far = _means([s.far for s in group])
        lines.append(
            f"| {world} | {t} | {g_near:.3f} / {g_far:.3f} | {c_near:.3f} / {c_far:.3f} "
            f"| {a_near:.3f} / {a_far:.3f} |"
        )
    return "\n".join(lines)


def format_ceiling_table(scores: list[SnapshotScore], settings: PredictorEvaluationConfig) -> str:
    """Markdown table: G and classical IoU against the near-only ceiling and the target."""
    metres = settings.near_known_cells * RESOLUTION_M
    margin = settings.target_margin_iou
    lines = [
        f"Against the best a local predictor could do (the ground truth within {metres:g} m of "
        f"a known cell, free beyond) and the target (classical + {margin:.2f}):",
        "",
        f"| map | t | IoU classical | IoU G | IoU perfect within {metres:g} m | "
        f"classical + {margin:.2f} | IoU G, no walls outside the building |",
        "|---|---|---|---|---|---|---|",
    ]
    for (world, t), group in _groups(scores):
        g, c, _, _ = _means([s.all for s in group])
        ceiling = float(np.mean([s.local_ceiling for s in group]))
        inside_only = float(np.mean([s.g_inside_only for s in group]))
        lines.append(
            f"| {world} | {t} | {c:.3f} | {g:.3f} | {ceiling:.3f} | {c + margin:.3f} "
            f"| {inside_only:.3f} |"
        )
    return "\n".join(lines)


def _groups(scores: list[SnapshotScore]) -> list[tuple[tuple[str, int | str], list]]:
    """(map, t) groups in order, then ("all", "-") with every score."""
    groups: dict[tuple[str, int | str], list[SnapshotScore]] = {}
    for score in scores:
        groups.setdefault((score.world, score.t), []).append(score)
    return [*groups.items(), (("all", "-"), scores)]


def _means(cells: list[CellScores]) -> tuple[float, float, float, float]:
    """Mean IoUs (G, classical, unknown = free) and mean AUROC (NaNs skipped)."""
    return (
        float(_nanmean([c.iou_g for c in cells])),
        float(_nanmean([c.iou_classical for c in cells])),
        float(_nanmean([c.iou_unknown_free for c in cells])),
        float(_nanmean([c.auroc for c in cells])),
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mapex.training.evaluate", description=__doc__)
    maps = parser.add_mutually_exclusive_group()
    maps.add_argument(
        "--maps",
        nargs="+",
        default=[str(path) for path in validation_map_dirs()],
        metavar="SPEC",
        help="worlds to take snapshots of: map directories or any world spec (default: the "
        "six validation maps, mapex.worlds.data)",
    )
    maps.add_argument(
        "--kth",
        action="store_true",
        help="the 18 KTH validation floors instead: 50037764_PLAN1, 50052748 and the held-out "
        "kth_sdf floors (mapex.worlds.data.KTH_SDF_VALIDATION_FLOORS)",
    )
    defaults = PredictorEvaluationConfig()
    parser.add_argument(
        "--times", nargs="+", type=int, default=list(defaults.snapshot_times), help="steps"
    )
    parser.add_argument("--figure", type=Path, default=None, help="write a PNG of one snapshot")
    parser.add_argument(
        "--weights",
        type=Path,
        default=WEIGHTS_DIR,
        help="the ensemble to score: a folder written by mapex.training.train --out "
        "(default: the shipped weights)",
    )
    parser.add_argument(
        "--reference-weights",
        type=Path,
        default=REFERENCE_WEIGHTS_DIR,
        help="the ensemble whose G is compared (default: %(default)s, the v2 weights)",
    )
    parser.add_argument("--no-reference", action="store_true", help="compare with no reference G")
    add_inference_arguments(parser)
    args = parser.parse_args(argv)
    settings = dataclasses.replace(defaults, snapshot_times=tuple(sorted(set(args.times))))
    if min(settings.snapshot_times) < 0:
        parser.error("--times must be >= 0")
    try:
        reference = None if args.no_reference else args.reference_weights
        inference = inference_from_args(args)
        specs = kth_validation_specs() if args.kth else args.maps
        scores = evaluate(specs, settings, args.figure, args.weights, inference, reference)
    except (WorldError, WeightsError) as error:
        print(f"mapex.training.evaluate: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    print(format_summary(scores, settings))
    print()
    print(format_map_table(scores, settings))
    print()
    print(format_table(scores))
    print()
    print(format_split_table(scores, settings.near_known_cells))
    print()
    print(format_ceiling_table(scores, settings))
    return 0


if __name__ == "__main__":
    sys.exit(main())
