"""G's decision threshold: chosen by IoU on training snapshots, stored as a logit bias."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from tiny_training import SMALL, TINY, tiny_overrides, tiny_snapshots
from torch import nn

import mapex.training.train as train
from mapex.grid import UNKNOWN
from mapex.prediction.learned import LearnedEnsemble
from mapex.prediction.network import LamaGenerator
from mapex.prediction.weights import (
    MEMBER_NAMES,
    read_logit_bias,
    read_metadata,
    save_weights,
    set_logit_bias,
)
from mapex.training.calibration import (
    calibrate,
    calibration_sample,
    iou_by_threshold,
    logit_bias,
)
from mapex.training.dataset import source_shares


@pytest.fixture(scope="module")
def snapshots():
    return tiny_snapshots()


class KnowsTheWalls(nn.Module):
    """A stand-in network read as the package reads it (`predict_logits`): wall probability
    `on_wall` on true walls, `off_wall` elsewhere. Its plain forward pass knows nothing
    (p = 0.5 everywhere), so a calibration that read that instead would choose otherwise."""

    def __init__(self, walls: np.ndarray, on_wall: float, off_wall: float) -> None:
        super().__init__()
        probability = np.where(walls, on_wall, off_wall).astype(np.float32)
        self.logits = nn.Parameter(torch.logit(torch.from_numpy(probability))[None, None])

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(inputs.shape[0], 1, *inputs.shape[-2:])

    def predict_logits(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.logits.expand(inputs.shape[0], 1, *inputs.shape[-2:])


@pytest.mark.parametrize("threshold", [0.2, 0.35, 0.5, 0.7])
def test_the_bias_moves_the_threshold_to_one_half(threshold):
    probabilities = torch.linspace(0.01, 0.99, 99)
    biased = torch.sigmoid(torch.logit(probabilities) + logit_bias(threshold))
    assert torch.equal(biased >= 0.5, probabilities >= threshold - 1e-6)


@pytest.mark.parametrize("threshold", [0.0, 1.0, -0.1])
def test_thresholds_outside_the_open_interval_are_refused(threshold):
    with pytest.raises(ValueError, match="strictly between 0 and 1"):
        logit_bias(threshold)


def test_iou_by_threshold_counts_only_the_given_cells():
    truth = np.array([[True, True, False, False]])
    probability = np.array([[0.9, 0.3, 0.3, 0.1]])
    cells = np.array([[True, True, True, False]])
    np.testing.assert_allclose(
        iou_by_threshold(probability, truth, cells, (0.2, 0.5, 0.95)), [2 / 3, 1 / 2, 0.0]
    )


def test_the_sample_is_seeded_and_without_repeats(snapshots):
    config = dataclasses.replace(TINY, calibration_snapshots=2)
    first = calibration_sample(snapshots, config)
    assert len(first) == 2 == len(set(first.tolist()))
    np.testing.assert_array_equal(first, calibration_sample(snapshots, config))
    everything = dataclasses.replace(TINY, calibration_snapshots=1000)
    assert len(calibration_sample(snapshots, everything)) == len(snapshots.observed)


def test_calibration_picks_the_threshold_with_the_best_iou(snapshots):
    walls = snapshots.worlds[0].occupancy
    model = KnowsTheWalls(walls, on_wall=0.3, off_wall=0.1)
    config = dataclasses.replace(TINY, calibration_thresholds=(0.05, 0.25, 0.5))
    calibration = calibrate(model, snapshots, config)
    assert calibration.threshold == 0.25  # separates walls from the rest; 0.5 finds none
    assert calibration.logit_bias == pytest.approx(math.log(3))
    ious = calibration.mean_iou_by_threshold
    assert ious["0.250"] == 1.0 and ious["0.500"] == 0.0 and 0 < ious["0.050"] < 1
    assert calibration.snapshots == len(snapshots.observed)
    assert calibration.shares == source_shares(config, config.polish_sources)  # mix on record


def test_the_stored_bias_shifts_only_that_members_logits(tmp_path):
    for index, name in enumerate(MEMBER_NAMES):
        torch.manual_seed(index)
        save_weights(tmp_path / f"{name}.pt", LamaGenerator(SMALL), {"member": name})
    observed = np.full((40, 52), UNKNOWN, dtype=np.uint8)
    before = LearnedEnsemble(tmp_path).predict_members(observed, (0, 1))
    set_logit_bias(tmp_path / "g.pt", 1.5, {"threshold": 0.18})
    after = LearnedEnsemble(tmp_path).predict_members(observed, (0, 1))
    shift = torch.logit(torch.from_numpy(after[0])) - torch.logit(torch.from_numpy(before[0]))
    torch.testing.assert_close(shift, torch.full_like(shift, 1.5), atol=1e-3, rtol=0)
    np.testing.assert_array_equal(after[1], before[1])
    assert read_metadata(tmp_path / "g.pt")["calibration"] == {"threshold": 0.18}
    assert read_logit_bias(tmp_path / "g1.pt") == 0.0


def test_calibrate_only_stores_a_threshold_from_the_grid(snapshots, tmp_path, capsys):
    train.train_member(0, snapshots, TINY, torch.device("cpu"), tmp_path, False)
    train.polish_main(snapshots, TINY, torch.device("cpu"), tmp_path, False)
    argv = ["--calibrate-only", "--out", str(tmp_path), "--no-kth", *tiny_overrides()]
    assert train.main(argv) == 0
    calibration = read_metadata(tmp_path / "g.pt")["calibration"]
    assert calibration["threshold"] in TINY.calibration_thresholds
    assert read_logit_bias(tmp_path / "g.pt") == pytest.approx(logit_bias(calibration["threshold"]))
    assert capsys.readouterr().out.startswith("g's threshold: ")


def test_calibrate_only_without_g_is_a_one_line_error(tmp_path, capsys):
    status = train.main(["--calibrate-only", "--out", str(tmp_path), "--no-kth"])
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(error) == 1 and "no weights file" in error[0]
