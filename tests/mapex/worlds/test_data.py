"""The validation split: fixed in code, disjoint from training, and refused by training."""

from __future__ import annotations

import re

import pytest
from tiny_training import TINY

from mapex.training.dataset import explore_snapshots, spec_name, training_world_specs
from mapex.training.train import build_parser
from mapex.worlds.data import (
    IPA_DIR,
    IPA_HELD_OUT_MAPS,
    IPA_MAPS,
    IPA_TRAINING_MAPS,
    IPA_VALIDATION_MAPS,
    KTH_SDF_DIR,
    KTH_SDF_VALIDATION_FLOORS,
    KTH_TRAINING_MAPS,
    KTH_VALIDATION_MAPS,
    NEVER_TRAIN_ON,
    kth_sdf_training_floors,
    kth_validation_specs,
    never_train_on,
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


NEEDS_KTH_SDF = pytest.mark.skipif(
    not (KTH_SDF_DIR / "train").is_dir(), reason="../shared/data/kth_sdf is not present"
)


def _id_number(floor: str) -> int:
    return int(re.match(r"\d+", floor).group())


@NEEDS_KTH_SDF
def test_the_kth_validation_floors_are_whole_buildings_of_kth_sdf():
    present = {p.stem for p in (KTH_SDF_DIR / "train").glob("*.world")}
    assert set(KTH_SDF_VALIDATION_FLOORS) <= present
    trainable = kth_sdf_training_floors()
    assert not set(trainable) & set(KTH_SDF_VALIDATION_FLOORS)
    # no trained floor is a floor of a held-out building (floor ids at most 3 apart)
    held = [_id_number(f) for f in KTH_SDF_VALIDATION_FLOORS]
    assert all(min(abs(_id_number(f) - h) for h in held) > 3 for f in trainable)
    assert len(trainable) + len(KTH_SDF_VALIDATION_FLOORS) + 1 == len(present)  # + 1 flagged


def test_kth_validation_specs_are_the_official_floors_then_the_held_out_ones():
    specs = kth_validation_specs()
    assert [spec_name(s) for s in specs] == [*KTH_VALIDATION_MAPS, *KTH_SDF_VALIDATION_FLOORS]
    assert all(never_train_on(spec_name(s)) for s in specs)


@pytest.mark.parametrize("name", KTH_SDF_VALIDATION_FLOORS[:3])
def test_training_refuses_a_held_out_kth_floor_in_any_form(name, tmp_path):
    for spec in (f"kth-sdf:{name}", f"{tmp_path / name}.world@scale=0.5"):
        with pytest.raises(ValueError, match="never train on it"):
            explore_snapshots(spec, TINY)
