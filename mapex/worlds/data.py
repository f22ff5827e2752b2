"""Where the development data lives, and which of it may be trained on
(docs/algorithms.md#worlds).

The data sits beside the checkout in `../shared/data` (never in the project): KTH floors
(`kth_dev/`, and 126 more as Gazebo worlds in `kth_sdf/train/`), IPA building maps (`ipa/`,
the KTH directory format) and HouseExpo house
plans (`houseexpo/plans.npz`). The validation split is fixed here, in code: its maps, and
every other rendering of their buildings, never enter training data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from mapex.worlds.base import (
    CORRIDOR_PREFIX,
    GENERATED_PREFIX,
    HOUSE_PREFIX,
    KTH_SDF_PREFIX,
    OPEN_GENERATED_PREFIX,
)

SHARED_DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data"
KTH_DEV_DIR = SHARED_DATA_DIR / "kth_dev"
IPA_DIR = SHARED_DATA_DIR / "ipa"
HOUSEEXPO_PLANS = SHARED_DATA_DIR / "houseexpo" / "plans.npz"
KTH_SDF_DIR = SHARED_DATA_DIR / "kth_sdf"
KTH_SDF_SPLITS = ("train", "check")  # the folders of kth_sdf holding <id>.world files

KTH_TRAINING_MAPS = ("50015847", "50015848")
KTH_VALIDATION_MAPS = ("50037764_PLAN1", "50052748")

# Two clean drawn plans (an office floor and a university library) and two SLAM-scanned
# buildings with their clutter (a lab and the Intel Research lab).
IPA_VALIDATION_MAPS = ("office_d", "NLB", "lab_a", "intel_map")
# Other renderings of the validation buildings (the IPA README's "same building"): held
# out with them, neither trained nor evaluated on.
IPA_HELD_OUT_MAPS = ("lab_a_scan", "lab_intel")
IPA_TRAINING_MAPS = (
    "Freiburg101_scan",
    "freiburg_building101",
    "lab_b",
    "lab_b_scan",
    "lab_e",
    "lab_f_scan",
    "lab_ipa",
    "map",
    "office_a",
    "office_b",
    "office_c",
    "office_g",
    "office_h",
    "office_i",
)
IPA_MAPS = IPA_TRAINING_MAPS + IPA_VALIDATION_MAPS + IPA_HELD_OUT_MAPS

# Our own KTH validation: whole buildings of kth_sdf/train held out (16 floors of 4
# buildings). Drawn once, seeded: the floors grouped into buildings by id (ids at most 3
# apart), 50015847's building left in training (v2's training floors), the groups shuffled
# with numpy's default_rng(63) and taken in that order until 15 floors were held out.
KTH_SDF_VALIDATION_FLOORS = (
    "50053292",
    "50053293",
    "0510032266_A_40_1_103",
    "0510032267_A_40_1_101",
    "0510032268_A_40_1_102",
    "0510032270_A_40_1_104",
    "0510032271_A_40_1_105",
    "0510030937_A_40_1_106",
    "0510030938_A_40_1_102",
    "0510030939_A_40_1_103",
    "0510030940_A_40_1_104",
    "0510030941_A_40_1_105",
    "0510030942_A_40_1_101",
    "50055637",
    "50055638",
    "50055639",
)
# floors the converter's authors flagged as broken (kth_sdf/flagged_worlds.txt): not trained on
KTH_SDF_FLAGGED = ("0510032192_A_40_1_203", "50037764_PLAN2")

VALIDATION_MAPS = KTH_VALIDATION_MAPS + IPA_VALIDATION_MAPS
NEVER_TRAIN_ON = VALIDATION_MAPS + IPA_HELD_OUT_MAPS + KTH_SDF_VALIDATION_FLOORS


def validation_map_dirs() -> list[Path]:
    """The six validation map directories: 2 KTH floors, then 4 IPA buildings."""
    return [KTH_DEV_DIR / name for name in KTH_VALIDATION_MAPS] + [
        IPA_DIR / name for name in IPA_VALIDATION_MAPS
    ]


def kth_validation_specs() -> list[str]:
    """The KTH validation floors as world specs: the two official ones (the authors'
    rasters in kth_dev), then our held-out kth_sdf floors."""
    official = [str(KTH_DEV_DIR / name) for name in KTH_VALIDATION_MAPS]
    return official + [f"{KTH_SDF_PREFIX}{name}" for name in KTH_SDF_VALIDATION_FLOORS]


def kth_sdf_training_floors(directory: Path = KTH_SDF_DIR / "train") -> list[str]:
    """The ids of the kth_sdf floors that may be trained on: every `<id>.world` in
    `directory` but the held-out, validation and flagged ones, sorted."""
    ids = sorted(path.stem for path in directory.glob("*.world"))
    return [i for i in ids if not never_train_on(i) and i not in KTH_SDF_FLAGGED]


def never_train_on(world_name: str) -> bool:
    """Whether a world of this name is validation data (or shares a building with it)."""
    return world_name in NEVER_TRAIN_ON


Source = Literal["houseexpo", "ipa", "kth", "procedural"]
SOURCES: tuple[Source, ...] = ("houseexpo", "ipa", "kth", "procedural")


def world_source(world_name: str) -> Source:
    """Where a world comes from, by its name: HouseExpo plans, an IPA map, our procedural
    plans, or (any other map directory) a KTH floor."""
    if world_name.startswith((HOUSE_PREFIX, CORRIDOR_PREFIX)):
        return "houseexpo"
    if world_name.startswith((GENERATED_PREFIX, OPEN_GENERATED_PREFIX)):
        return "procedural"
    return "ipa" if world_name in IPA_MAPS else "kth"
