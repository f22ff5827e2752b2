"""G's decision threshold: the wall probability from which a cell counts as occupied.

The metrics and the thresholded-map methods read G at p >= 0.5 (docs/algorithms.md#metrics). G is
trained with wall-weighted cross-entropy, which fixes its operating point only
roughly, and for a rare class such as walls the IoU-optimal threshold of a
probability lies well below 0.5. Calibration measures G's mean occupied-class IoU
over the unknown footprint cells of *training* snapshots (never the validation
maps) for a grid of thresholds, and stores the best one as a bias on G's logits,
so that "G thresholded at 0.5" is G thresholded at the chosen value. The members
G_1..G_3 keep a zero bias: their mean and variance drive MapEx as trained.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mapex.config import MetricsConfig
from mapex.grid import UNKNOWN
from mapex.metrics import building_footprint, occupied_iou
from mapex.prediction.config import PredictorTrainingConfig
from mapex.prediction.network import LamaGenerator, encode_observed
from mapex.prediction.weights import load_member, set_logit_bias
from mapex.training.dataset import SnapshotSet, snapshot_probabilities, source_shares


@dataclass(frozen=True)
class Calibration:
    """The chosen threshold, its logit bias and the evidence: mean IoU per threshold."""

    threshold: float
    logit_bias: float
    snapshots: int
    shares: dict[str, float]  # the sample's mix of sources (the polish crops' mix)
    mean_iou_by_threshold: dict[str, float]  # "0.30" -> mean IoU over the snapshots


def logit_bias(threshold: float) -> float:
    """The bias that moves a probability `threshold` to 0.5: -logit(threshold)."""
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"a threshold must lie strictly between 0 and 1 (got {threshold})")
    return -math.log(threshold / (1.0 - threshold))


def iou_by_threshold(
    probability: np.ndarray, truth: np.ndarray, cells: np.ndarray, thresholds: tuple[float, ...]
) -> np.ndarray:
    """Occupied-class IoU over `cells` (bool) of `probability` >= each threshold."""
    return np.array([occupied_iou(probability >= t, truth, cells) for t in thresholds])


def calibration_sample(snapshots: SnapshotSet, config: PredictorTrainingConfig) -> np.ndarray:
    """Indices of the snapshots to calibrate on: `calibration_snapshots` drawn without
    replacement with the polish crops' mix of sources (seeded)."""
    probabilities = snapshot_probabilities(snapshots, source_shares(config, config.polish_sources))
    count = min(config.calibration_snapshots, int(np.count_nonzero(probabilities)))
    rng = np.random.default_rng(config.seed)
    return np.sort(rng.choice(len(probabilities), size=count, replace=False, p=probabilities))


def calibrate(
    model: LamaGenerator, snapshots: SnapshotSet, config: PredictorTrainingConfig
) -> Calibration:
    """The threshold (from `config.calibration_thresholds`) at which `model`'s mean
    unknown-cell IoU over a sample of `snapshots` is highest."""
    thresholds = config.calibration_thresholds
    margin = MetricsConfig().footprint_margin_cells
    footprints = [building_footprint(w.valid_space, margin) for w in snapshots.worlds]
    device = next(model.parameters()).device
    ious = []
    for index in tqdm(calibration_sample(snapshots, config), desc="calibrate g", unit="snapshot"):
        observed = snapshots.observed[index]
        world = int(snapshots.world_of[index])
        inputs = torch.from_numpy(encode_observed(observed))[None].to(device)
        with torch.inference_mode():
            probability = torch.sigmoid(model.predict_logits(inputs))[0, 0].float().cpu().numpy()
        cells = (observed == UNKNOWN) & footprints[world]
        truth = snapshots.worlds[world].occupancy
        ious.append(iou_by_threshold(probability, truth, cells, thresholds))
    means = np.mean(ious, axis=0)
    best = thresholds[int(np.argmax(means))]
    return Calibration(
        threshold=best,
        logit_bias=logit_bias(best),
        snapshots=len(ious),
        shares=source_shares(config, config.polish_sources),
        mean_iou_by_threshold={
            f"{t:.3f}": round(float(m), 4) for t, m in zip(thresholds, means, strict=True)
        },
    )


def calibrate_weights(
    path: Path, snapshots: SnapshotSet, config: PredictorTrainingConfig
) -> Calibration:
    """Calibrate the network stored at `path` and store its logit bias there."""
    model = load_member(path)
    calibration = calibrate(model, snapshots, config)
    set_logit_bias(path, calibration.logit_bias, asdict(calibration))
    return calibration


def describe(calibration: Calibration) -> str:
    """One line: the chosen threshold and the IoU it gives against 0.5."""
    ious = calibration.mean_iou_by_threshold
    at_half = ious.get("0.500")
    versus = f" (at 0.5: {at_half:.3f})" if at_half is not None else ""
    return (
        f"g's threshold: {calibration.threshold:.3f}, mean IoU "
        f"{ious[f'{calibration.threshold:.3f}']:.3f}{versus} over {calibration.snapshots} "
        f"training snapshots; logit bias {calibration.logit_bias:+.3f}"
    )
