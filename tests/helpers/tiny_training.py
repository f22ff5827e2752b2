"""A network and a training set-up small enough for tests that train in seconds."""

from __future__ import annotations

import numpy as np

from mapex.prediction.config import NetworkConfig, PredictorTrainingConfig
from mapex.training.dataset import SnapshotSet, explore_snapshots, training_world_specs
from mapex.worlds import load_world

SMALL = NetworkConfig(channels=16, n_blocks=1, downscale=4, refine_channels=4)
TINY = PredictorTrainingConfig(
    procedural_worlds=1,
    houseexpo_worlds=0,
    use_ipa=False,
    member_sources=("procedural",) * 3,
    snapshot_steps=120,
    snapshot_every_steps=40,
    starts_per_world=1,
    snapshot_methods=("nearest",),
    crop_cells=64,
    batch_size=2,
    main_steps=4,
    member_steps=2,
    main_polish_steps=2,
    checkpoint_every_steps=2,
    precision="float32",  # fast on every CPU
    network=SMALL,
)


# Command-line flags that leave out every source but the procedural plans (fast tests).
PROCEDURAL_ONLY = ["--no-kth", "--set", "houseexpo_worlds=0", "--set", "use_ipa=false"]


def tiny_overrides() -> list[str]:
    """`--set` arguments that make the training command's data, network and schedule TINY's."""
    fields = {
        "procedural_worlds": TINY.procedural_worlds,
        "houseexpo_worlds": TINY.houseexpo_worlds,
        "use_ipa": TINY.use_ipa,
        "member_sources": ",".join(TINY.member_sources),
        "snapshot_steps": TINY.snapshot_steps,
        "snapshot_every_steps": TINY.snapshot_every_steps,
        "starts_per_world": TINY.starts_per_world,
        "snapshot_methods": ",".join(TINY.snapshot_methods),
        "main_polish_steps": TINY.main_polish_steps,
        "main_steps": TINY.main_steps,
        "member_steps": TINY.member_steps,
        "crop_cells": TINY.crop_cells,
        "batch_size": TINY.batch_size,
        "checkpoint_every_steps": TINY.checkpoint_every_steps,
        "precision": TINY.precision,
        **{f"network.{name}": value for name, value in vars(SMALL).items()},
    }
    return [arg for name, value in fields.items() for arg in ("--set", f"{name}={value}")]


def tiny_snapshots() -> SnapshotSet:
    """The snapshots of TINY's one procedural world (3 of them)."""
    spec = training_world_specs(TINY, [])[0]
    observed = explore_snapshots(spec, TINY)
    return SnapshotSet([load_world(spec)], observed, np.zeros(len(observed), dtype=np.int64))
