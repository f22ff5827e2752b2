"""The validation split: fixed in code, disjoint from training, and refused by training."""

from __future__ import annotations

import pytest
from tiny_training import TINY

from mapex.training.dataset import explore_snapshots, training_world_specs
from mapex.training.train import build_parser
from mapex.worlds.data import (
    IPA_DIR,
    IPA_HELD_OUT_MAPS,
    IPA_MAPS,
    IPA_TRAINING_MAPS,
    IPA_VALIDATION_MAPS,
    KTH_TRAINING_MAPS,
    KTH_VALIDATION_MAPS,
    NEVER_TRAIN_ON,
    validation_map_dirs,
    world_source,
)


def test_the_split_is_disjoint_and_names_six_validation_maps():
    assert not set(IPA_TRAINING_MAPS) & set(NEVER_TRAIN_ON)
    assert not set(KTH_TRAINING_MAPS) & set(NEVER_TRAIN_ON)
    assert len(set(IPA_MAPS)) == len(IPA_MAPS)
    assert [d.name for d in validation_map_dirs()] == [*KTH_VALIDATION_MAPS, *IPA_VALIDATION_MAPS]
    assert len(IPA_VALIDATION_MAPS) == 4


def test_the_split_covers_every_ipa_map_there_is():
    if not IPA_DIR.is_dir():
        pytest.skip("../shared/data/ipa is not present")
    present = {p.name for p in IPA_DIR.iterdir() if p.is_dir()}
    assert present == set(IPA_MAPS)


@pytest.mark.parametrize("name", NEVER_TRAIN_ON)
def test_training_refuses_every_validation_and_held_out_map(name):
    folder = "kth_dev" if name in KTH_VALIDATION_MAPS else "ipa"
    with pytest.raises(ValueError, match=f"{name} is a validation map"):
        training_world_specs(TINY, [], [f"../shared/data/{folder}/{name}/"])


@pytest.mark.parametrize("name", IPA_HELD_OUT_MAPS + KTH_VALIDATION_MAPS)
def test_snapshot_collection_refuses_a_validation_world_however_it_is_named(name, tmp_path):
    with pytest.raises(ValueError, match="never train on it"):
        explore_snapshots(str(tmp_path / name), TINY)  # refused before the map is read


def test_the_training_command_trains_on_no_validation_map():
    config = type(TINY)()
    args = build_parser().parse_args([])
    kth = [str(args.kth_dir / m) for m in KTH_TRAINING_MAPS]
    ipa = [str(args.ipa_dir / m) for m in IPA_TRAINING_MAPS]
    specs = training_world_specs(config, kth, ipa)
    assert not {spec.rstrip("/").split("/")[-1] for spec in specs} & set(NEVER_TRAIN_ON)
    assert {world_source(s.split("/")[-1]) for s in specs} == {
        "houseexpo",
        "ipa",
        "kth",
        "procedural",
    }
