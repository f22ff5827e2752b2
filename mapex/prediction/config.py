"""Settings of the map predictors: network size, training recipe, evaluation, the classical
ensemble, and the forward-pass precision. Overridable with `--set` like every other
configuration (`mapex.config.apply_overrides`)."""

from __future__ import annotations

import argparse
import typing
from dataclasses import dataclass, field
from typing import Literal

from mapex.config import MAX_SEED, Checked, ConfigError, positive, ranged, share
from mapex.worlds.data import IPA_TRAINING_MAPS

Precision = Literal["float32", "bfloat16"]


PRECISIONS: tuple[str, ...] = typing.get_args(Precision)


@dataclass(frozen=True)
class NetworkConfig(Checked):
    """Size of the LaMa-style generator (mapex/prediction/network.py)."""

    SECTION = "network"
    channels: int = ranged(64, 1)
    n_blocks: int = ranged(4, 0)  # FFC residual blocks
    downscale: int = ranged(8, 1)  # the FFC trunk works at 1/downscale resolution (pixel unshuffle)
    global_ratio: float = share(0.75)  # share of channels in the spectral (global) branch
    refine_channels: int = ranged(16, 1)  # full-resolution refinement of the upsampled logits
    context_cells: int = ranged(32, 0)  # map around a predicted region that the network also sees
    # inference: average the logits over the map and the map turned by 180 degrees (two
    # forward passes); the network is not equivariant, and the two views' errors differ
    average_turned_view: bool = True


MemberSplit = Literal["thirds", "by_source", "bagged"]


@dataclass(frozen=True)
class PredictorTrainingConfig(Checked):
    """Data and schedule of `python -m mapex.training.train` (docs/prediction.md#training).

    Sources (mapex.worlds.data.SOURCES): "houseexpo" (houses along a corridor), "ipa" (IPA
    training maps), "kth" (the two KTH training floors of kth_dev and, with `kth_sdf`, the
    trainable floors of kth_sdf/train), "procedural" (our plans)."""

    procedural_worlds: int = ranged(32, 0)  # generated-open:<first_procedural_seed + i>
    first_procedural_seed: int = ranged(1000, 0, MAX_SEED)
    houseexpo_worlds: int = ranged(48, 0)  # houseexpo-corridor:<first_houseexpo_seed + i>
    first_houseexpo_seed: int = ranged(0, 0, MAX_SEED)
    use_ipa: bool = True  # explore the IPA maps `ipa_maps` (in --ipa-dir)
    # explore the kth_sdf/train floors (in --kth-sdf-dir) but the held-out and flagged ones
    kth_sdf: bool = True
    ipa_maps: tuple[str, ...] = IPA_TRAINING_MAPS
    snapshot_methods: tuple[str, ...] = ("nearest", "observed_map")
    starts_per_world: int = ranged(2, 1)  # procedural plans and HouseExpo worlds
    ipa_starts_per_world: int = ranged(2, 1)
    kth_starts_per_world: int = ranged(2, 1)
    # Share of G's pretraining crops per source (renormalised over the sources present);
    # a member's crops keep these proportions within its own sources.
    houseexpo_share: float = ranged(0.1, 0)
    ipa_share: float = ranged(0.25, 0)
    kth_share: float = ranged(0.5, 0)
    procedural_share: float = ranged(0.15, 0)
    snapshot_steps: int = ranged(1000, 1)
    snapshot_every_steps: int = ranged(50, 1)
    crop_cells: int = ranged(256, 1)
    frontier_share: float = share(0.75)  # crops centred near a frontier, the rest anywhere
    edge_overhang_cells: int = ranged(64, 0)  # how far a crop may hang over the map's border
    batch_size: int = ranged(8, 1)
    main_steps: int = ranged(10000, 0)  # G's pretraining, on every source
    member_steps: int = ranged(1500, 0)  # G_1..G_3 each
    # G_1..G_3 fine-tune G's pretrained weights (v2, v3; the paper fine-tunes one LaMa) or,
    # when False, start from their own random weights (needs a longer member_steps)
    members_from_main: bool = True
    # G_k's data: "bagged" = a seeded random `bag_share` of the worlds of every source (its
    # own draw per member); "by_source" = the k-th entry of member_sources ("+" joins
    # sources); "thirds" = the worlds whose index is k - 1 modulo 3.
    member_split: MemberSplit = "bagged"
    bag_share: float = ranged(0.67, 0, 1, low_open=True)
    member_sources: tuple[str, ...] = ("houseexpo", "ipa", "kth+procedural")
    # Procedural plans with free space outside the building (generated-open:SEED), as in
    # the KTH maps, instead of solid wall.
    free_outside_plans: bool = True
    learning_rate: float = positive(2e-3)
    # of each run's steps spent raising the learning rate (one cycle)
    warmup_share: float = ranged(0.1, 0, 1, low_open=True, high_open=True)
    weight_decay: float = ranged(1e-4, 0)
    wall_weight: float = ranged(2.0, 0)  # BCE weight of wall cells (walls are the rarer class)
    # the same for G_1..G_3's fine-tuning (plain cross-entropy)
    member_wall_weight: float = ranged(1.0, 0)
    # After G_1..G_3 have started from it, G is polished: fine-tuned further on the
    # office-like sources `polish_sources` with this many steps of its loss plus
    # `polish_soft_iou_weight` times a soft IoU of the walls per crop (the metric the
    # evaluation scores), at `polish_learning_rate`. 0: no polish.
    main_polish_steps: int = ranged(1500, 0)
    polish_sources: tuple[str, ...] = ("ipa", "kth", "procedural")
    polish_soft_iou_weight: float = ranged(3.0, 0)
    # and this many times a soft IoU over the unknown cells farther than `far_cells` from
    # any known cell of the crop alone: the walls of rooms nobody has seen, which the whole
    # crop's IoU leaves to the near cells' many walls (0: none)
    polish_far_soft_iou_weight: float = ranged(3.0, 0)  # v3
    far_cells: int = ranged(10, 1)  # 1 m, as the evaluation's "near" (Chebyshev, in cells)
    polish_learning_rate: float = positive(1e-3)
    # G is polished this many times from its base weights (seeds seed + 4, + 5, ...) and
    # g.pt is the mean of the polished weights (a uniform model soup). 1: one polish.
    polish_runs: int = ranged(1, 1)
    calibrate_main: bool = True  # after training G, choose its decision threshold (IoU)
    calibration_snapshots: int = ranged(200, 1)  # training snapshots G's threshold is chosen on
    calibration_thresholds: tuple[float, ...] = share(
        tuple(round(0.2 + 0.025 * i, 3) for i in range(17))
    )
    checkpoint_every_steps: int = ranged(100, 1)
    seed: int = ranged(0, 0, MAX_SEED)
    # processes cutting crops (for a GPU); the count changes the crop order
    data_workers: int = ranged(0, 0)
    # Forward pass in training. "bfloat16" autocasts it (weights, loss and optimiser stay
    # float32): about twice as fast on CPUs with AVX512-BF16 and on GPUs (slower on other
    # CPUs). The shipped weights were trained in bfloat16; "float32" writes other weights.
    precision: Precision = "bfloat16"
    network: NetworkConfig = field(default_factory=NetworkConfig)  # size of every member


@dataclass(frozen=True)
class PredictorEvaluationConfig(Checked):
    """`python -m mapex.training.evaluate` (docs/algorithms.md#prediction): when snapshots are
    taken, and what
    counts as near the known map."""

    snapshot_times: tuple[int, ...] = ranged((100, 300, 600), 0)
    near_known_cells: int = ranged(10, 0)  # 1 m: unknown cells this close to a known one are "near"
    # 2 m: the variance beyond this distance from the known map is "far"
    far_cells: int = ranged(20, 0)
    target_margin_iou: float = share(0.10)  # the lead over the classical IoU that G should reach


InpaintMethod = Literal["ns", "telea"]


@dataclass(frozen=True)
class InpaintMemberConfig(Checked):
    """One member of the classical inpainting ensemble (mapex.prediction.classical)."""

    SECTION = "member"
    method: InpaintMethod = "ns"  # cv2.INPAINT_NS (Navier-Stokes) or cv2.INPAINT_TELEA
    radius_cells: int = ranged(1, 1)  # cv2.inpaint neighbourhood radius, in working-scale cells
    scale: int = ranged(1, 1)  # works at 1/scale resolution (walls block-max downsampled) when > 1
    # only unknown cells this close (map cells) to known ones are painted
    band_cells: float = ranged(8.0, 0)
    prior: float = share(0.05)  # wall probability of the unknown cells beyond the band
    # painted value mapped to 0.5 by a piecewise-linear contrast
    wall_level: float = ranged(0.5, 0, 1, low_open=True, high_open=True)


@dataclass(frozen=True)
class ClassicalPredictorConfig(Checked):
    """The classical (non-learned) predictor ensemble; member 0 is G (best single setting)."""

    members: tuple[InpaintMemberConfig, ...] = (
        InpaintMemberConfig(method="ns", radius_cells=1, scale=1, band_cells=10.0, prior=0.05),
        InpaintMemberConfig(method="ns", radius_cells=3, scale=2, band_cells=6.0, prior=0.0),
        InpaintMemberConfig(method="ns", radius_cells=1, scale=4, band_cells=8.0, prior=0.1),
        InpaintMemberConfig(
            method="telea", radius_cells=1, scale=4, band_cells=6.0, prior=0.15, wall_level=0.3
        ),
    )


InferencePath = Literal["fused", "plain"]
INFERENCE_PATHS: tuple[str, ...] = typing.get_args(InferencePath)


@dataclass(frozen=True)
class InferenceConfig(Checked):
    """How the learned ensemble runs its networks (docs/benchmarks.md#the-predictor).

    `path`: "fused" (mapex.prediction.inference: batch norms folded, refinement in cached
    strips; the same logits to float32 rounding, about 1.4 times faster on one core) or
    "plain" (the training module as it is). `views`: 2 (the map and the map turned by 180
    degrees, logits averaged) or 1 (the map only: half the work, but G's IoU -0.008 and
    `mapex`'s coverage AUC -0.033 on the validation maps; docs/experiments.md).
    `precision`: float32, or bfloat16 autocast (not held to float32's agreement)."""

    precision: Precision = "float32"
    path: InferencePath = "fused"
    views: int = ranged(2, 1, 2)

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ConfigError(f"precision {self.precision!r}: choose from {', '.join(PRECISIONS)}")
        if self.path not in INFERENCE_PATHS:
            paths = ", ".join(INFERENCE_PATHS)
            raise ConfigError(f"path: inference {self.path!r}: choose from {paths}")
        if self.views not in (1, 2):
            raise ConfigError(f"views {self.views!r}: choose 1 or 2")
        super().__post_init__()

    def ensemble_options(self) -> dict:
        """Keyword arguments of `LearnedEnsemble` that run it this way."""
        return {"precision": self.precision, "inference": self.path, "views": self.views}

    def flags(self) -> tuple[str, ...]:
        """The command-line flags that give this configuration (for spawned workers)."""
        return ("--precision", self.precision, "--inference", self.path, "--views", str(self.views))


DEFAULT_INFERENCE = InferenceConfig()


def add_inference_arguments(parser: argparse.ArgumentParser) -> None:
    """--precision, --inference and --views of the learned ensemble (`inference_from_args`)."""
    parser.add_argument(
        "--precision",
        default="float32",
        choices=PRECISIONS,
        help="forward pass: float32 (default; the README's figures) or bfloat16 (about 2x "
        "faster on CPUs with AVX512-BF16/AMX and on GPUs, slower on other CPUs)",
    )
    parser.add_argument(
        "--inference",
        default="fused",
        choices=INFERENCE_PATHS,
        help="fused (default: batch norms folded, cache-sized refinement strips; the same "
        "probabilities to 1e-5) or plain (the training module, PyTorch as is)",
    )
    parser.add_argument(
        "--views",
        type=int,
        default=2,
        choices=(1, 2),
        help="network passes per prediction: 2 (default: the map and the map turned by 180 "
        "degrees, logits averaged) or 1 (half the time; mapex's coverage AUC -0.033 on the "
        "validation maps)",
    )


def inference_from_args(args: argparse.Namespace) -> InferenceConfig:
    """The InferenceConfig of the flags `add_inference_arguments` added."""
    return InferenceConfig(args.precision, args.inference, args.views)
