"""`python -m mapex.prediction.evaluate`: how good are the predictions, on their own?

On validation maps (never trained on), observed maps are taken from nearest-frontier
runs at t = 100, 300, 600 from all 4 starts. For each, the occupied-class IoU over
the *unknown* cells inside the building footprint (the part that is actually
predicted) is measured for G, for the classical predictor and for "unknown = free",
and the ensemble variance is scored as a detector of G's wrong cells (AUROC).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import rankdata
from tqdm import tqdm

from mapex.config import ExplorationConfig
from mapex.grid import UNKNOWN, observed_to_probability
from mapex.metrics import building_footprint, occupied_iou
from mapex.plotting import occupancy_image, plt
from mapex.prediction import make_predictor
from mapex.prediction.base import EnsemblePrediction
from mapex.prediction.dataset import snapshots_at
from mapex.prediction.weights import WeightsError
from mapex.worlds import WorldError, load_world, start_poses

KTH_DEV_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "kth_dev"
VALIDATION_MAPS = ("50037764_PLAN1", "50052748")
SNAPSHOT_TIMES = (100, 300, 600)


@dataclass
class SnapshotScore:
    """Scores of one snapshot: IoUs over unknown footprint cells and the variance AUROC."""

    world: str
    start: int
    t: int
    iou_g: float
    iou_classical: float
    iou_unknown_free: float
    auroc: float


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve of `scores` for boolean `labels` (ties count half)."""
    positives = int(labels.sum())
    negatives = labels.size - positives
    if positives == 0 or negatives == 0:
        return float("nan")
    ranks = rankdata(scores)
    return float((ranks[labels].sum() - positives * (positives + 1) / 2) / (positives * negatives))


def score_snapshot(
    truth: np.ndarray,
    cells: np.ndarray,
    learned: EnsemblePrediction,
    classical_main: np.ndarray,
    threshold: float,
) -> tuple[float, float, float, float]:
    """(IoU of G, IoU of classical, IoU of unknown = free, AUROC) over `cells` (bool)."""
    wrong = (learned.main >= threshold) != truth
    return (
        occupied_iou(learned.main >= threshold, truth, cells),
        occupied_iou(classical_main >= threshold, truth, cells),
        occupied_iou(np.zeros_like(truth), truth, cells),
        auroc(learned.variance[cells], wrong[cells]),
    )


def evaluate(
    map_dirs: list[Path], times: tuple[int, ...], figure: Path | None
) -> list[SnapshotScore]:
    """Score every (map, start, time) snapshot; optionally draw one of them."""
    learned, classical = make_predictor("lama"), make_predictor("classical")
    config = ExplorationConfig()
    threshold = config.metrics.prediction_threshold
    drawn = (map_dirs[-1], 0, times[len(times) // 2])  # which snapshot the figure shows
    scores = []
    jobs = [(d, s) for d in map_dirs for s in range(4)]
    for map_dir, start_index in tqdm(jobs, desc="exploring", unit="run"):
        world = load_world(str(map_dir))
        footprint = building_footprint(world.valid_space, config.metrics.footprint_margin_cells)
        start = start_poses(world, config.world.start_clearance_cells)[start_index]
        snapshots, _ = snapshots_at(world, "nearest", start, list(times))
        for t in times:
            observed = snapshots[t]
            prediction = learned.predict(observed)
            cells = (observed == UNKNOWN) & footprint
            classical_main = classical.predict_main(observed)
            values = score_snapshot(world.occupancy, cells, prediction, classical_main, threshold)
            scores.append(SnapshotScore(world.name, start_index, t, *values))
            if figure is not None and (map_dir, start_index, t) == drawn:
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


def format_table(scores: list[SnapshotScore]) -> str:
    """Markdown table: per map and time, means over the 4 starts, then the overall mean."""
    lines = [
        "| map | t | IoU G | IoU classical | IoU unknown=free | G - classical "
        "| AUROC var vs error |",
        "|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple[str, int], list[SnapshotScore]] = {}
    for score in scores:
        groups.setdefault((score.world, score.t), []).append(score)
    for (world, t), group in [*groups.items(), (("all", "-"), scores)]:
        g = np.mean([s.iou_g for s in group])
        c = np.mean([s.iou_classical for s in group])
        free = np.mean([s.iou_unknown_free for s in group])
        area = np.nanmean([s.auroc for s in group])
        lines.append(
            f"| {world} | {t} | {g:.3f} | {c:.3f} | {free:.3f} | {g - c:+.3f} | {area:.3f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mapex.prediction.evaluate", description=__doc__
    )
    parser.add_argument(
        "--maps",
        nargs="+",
        type=Path,
        default=[KTH_DEV_DIR / name for name in VALIDATION_MAPS],
        help="KTH map directories (default: the two validation maps)",
    )
    parser.add_argument("--times", nargs="+", type=int, default=list(SNAPSHOT_TIMES))
    parser.add_argument("--figure", type=Path, default=None, help="write a PNG of one snapshot")
    args = parser.parse_args(argv)
    try:
        scores = evaluate(args.maps, tuple(sorted(args.times)), args.figure)
    except (WorldError, WeightsError) as error:
        print(f"mapex.prediction.evaluate: error: {error}", file=sys.stderr)
        return 2
    print(format_table(scores))
    return 0


if __name__ == "__main__":
    sys.exit(main())
