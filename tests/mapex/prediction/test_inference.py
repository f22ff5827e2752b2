"""The fused inference path computes the training module's logits: on random networks with
non-trivial batch norms, at every size, and for every shipped member on development maps."""

import dataclasses

import numpy as np
import pytest
import torch
from tiny_training import SMALL

from mapex.bench import explored_state
from mapex.config import ExplorationConfig
from mapex.prediction.inference import FusedGenerator, SingleOutputConv
from mapex.prediction.learned import LearnedEnsemble
from mapex.prediction.network import OUTSIDE_MAP, LamaGenerator, encode_observed
from mapex.worlds import load_world


def random_network(config=SMALL, seed: int = 0) -> LamaGenerator:
    """A network whose every parameter and batch-norm statistic is random (a folded batch
    norm that was the identity would prove nothing)."""
    torch.manual_seed(seed)
    model = LamaGenerator(config)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.normal_(0.0, 0.3)
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.normal_(0.0, 0.5)
                module.running_var.uniform_(0.5, 2.0)
    return model.eval()


def random_observed(rows: int, cols: int, seed: int = 0) -> np.ndarray:
    codes = np.random.default_rng(seed).integers(0, 3, (rows, cols)).astype(np.uint8)
    codes[: rows // 5, : cols // 4] = OUTSIDE_MAP  # beyond the map's border: all zeros
    return codes


@pytest.mark.parametrize(
    "shape", [(1, 1), (7, 5), (16, 16), (37, 53), (64, 41), (130, 97)], ids=str
)
@pytest.mark.parametrize("strip_rows", [1, 5, 16, 200])
def test_fused_logits_equal_the_training_modules(shape, strip_rows):
    model = random_network()
    fused = FusedGenerator(model, strip_rows=strip_rows)
    codes = random_observed(*shape)
    inputs = torch.from_numpy(encode_observed(codes))[None]
    with torch.inference_mode():
        expected, got = model(inputs), fused(torch.from_numpy(codes)[None])
    assert got.shape == expected.shape == (1, 1, *shape)
    torch.testing.assert_close(got, expected, atol=1e-4, rtol=1e-4)


def test_fused_batches_and_both_views_agree():
    model = random_network(dataclasses.replace(SMALL, average_turned_view=True), seed=3)
    fused = FusedGenerator(model)
    codes = np.stack([random_observed(45, 70, seed=1), random_observed(45, 70, seed=2)])
    inputs = torch.from_numpy(np.stack([encode_observed(c) for c in codes]))
    with torch.inference_mode():
        torch.testing.assert_close(
            fused.predict_logits(torch.from_numpy(codes)),
            model.predict_logits(inputs),
            atol=1e-4,
            rtol=1e-4,
        )


def test_a_single_output_convolution_equals_torchs():
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(6, 1, 3, padding=(0, 1))
    hidden = torch.randn(2, 6, 9, 23).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        torch.testing.assert_close(SingleOutputConv(conv)(hidden), conv(hidden))
    with pytest.raises(ValueError, match="one channel"):
        SingleOutputConv(torch.nn.Conv2d(6, 2, 3))


def test_a_strip_of_no_rows_is_refused():
    with pytest.raises(ValueError, match="strip_rows"):
        FusedGenerator(random_network(), strip_rows=0)


@pytest.fixture
def development_snapshots(kth_dev_dir) -> list[np.ndarray]:
    """Observed maps of nearest-frontier runs on two development floors (t = 300, 150)."""
    return [
        explored_state(load_world(str(kth_dev_dir / name)), ExplorationConfig(), steps).observed
        for name, steps in (("50015847", 300), ("50037764_PLAN1", 150))
    ]


@pytest.mark.slow
def test_every_shipped_member_agrees_with_pytorch_on_development_maps(development_snapshots):
    """The fused path's probabilities equal the plain PyTorch module's within 1e-3, for every
    shipped member with two views (the default), and for G with one."""
    for views, members in ((2, (0, 1, 2, 3)), (1, (0,))):
        fused = LearnedEnsemble(inference="fused", views=views, recent_answers=0)
        plain = LearnedEnsemble(inference="plain", views=views, recent_answers=0)
        for observed in development_snapshots:
            difference = np.abs(
                fused.predict_members(observed, members) - plain.predict_members(observed, members)
            )
            assert difference.max() <= 1e-3, f"{observed.shape}: {difference.max():.2e}"
