"""`python -m mapex.training.train`: train the LaMa-style ensemble and write its weights.

G is pretrained on snapshots of every source of worlds (g-base.pt); G_1..G_3 each fine-tune
those weights on sources of their own (or on a disjoint third of the worlds with `--set
member_split=thirds`); then G is fine-tuned on the office-like sources with a soft IoU
added to its loss (`polish_main`) and its decision threshold is chosen on training
snapshots (`mapex.training.calibration`; `--calibrate-only` does that alone). Validation
maps are refused; an interrupted run resumes with `--resume`. The final weights (float16) go
to `mapex/prediction/weights/` by default, where the package loads them from. The recipe and
its data: docs/prediction.md#training."""

from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from tqdm import tqdm

from mapex.config import ConfigError, apply_overrides
from mapex.exit_codes import EXIT_USAGE
from mapex.prediction.config import MemberSplit, PredictorTrainingConfig
from mapex.prediction.network import LamaGenerator, autocast, emulated_bfloat16
from mapex.prediction.weights import (
    MEMBER_NAMES,
    WEIGHTS_DIR,
    WeightsError,
    load_member,
    read_metadata,
    save_weights,
)
from mapex.training.batches import batch_loader
from mapex.training.calibration import calibrate_weights, describe
from mapex.training.dataset import (
    CropSampler,
    SnapshotSet,
    cached_snapshots,
    spec_name,
    training_world_specs,
)
from mapex.worlds import WorldError
from mapex.worlds.data import (
    IPA_DIR,
    KTH_DEV_DIR,
    KTH_SDF_DIR,
    KTH_TRAINING_MAPS,
    SOURCES,
    kth_sdf_training_floors,
    world_source,
)
from mapex.worlds.gazebo import KTH_SDF_SCALE


def member_snapshots(
    snapshots: SnapshotSet,
    member: int,
    split: MemberSplit = "thirds",
    sources: tuple[str, ...] = (),
    bag_share: float = 0.67,
    seed: int = 0,
) -> SnapshotSet:
    """G (member 0) sees every snapshot. G_k sees, with "thirds", the worlds whose index is
    k - 1 modulo 3; with "by_source", the worlds of `member_source_set(sources, k)`; with
    "bagged", `bagged_worlds`."""
    if member == 0:
        return snapshots
    if split == "thirds":
        return snapshots.subset(snapshots.world_of % 3 == member - 1)
    if split == "bagged":
        worlds = bagged_worlds(snapshots, bag_share, seed + member)
        return snapshots.subset(np.isin(snapshots.world_of, worlds))
    wanted = member_source_set(sources, member)
    worlds = [i for i, w in enumerate(snapshots.worlds) if world_source(w.name) in wanted]
    return snapshots.subset(np.isin(snapshots.world_of, worlds))


def bagged_worlds(snapshots: SnapshotSet, share: float, seed: int) -> np.ndarray:
    """Indices of a seeded random `share` of the worlds of each source (at least one each):
    members trained on different bags of whole worlds disagree where the worlds they left
    out differ, which is what their variance should flag."""
    rng = np.random.default_rng(seed)
    sources = np.array([world_source(world.name) for world in snapshots.worlds])
    chosen = []
    for source in SOURCES:
        worlds = np.flatnonzero(sources == source)
        if len(worlds):
            count = max(1, round(share * len(worlds)))
            chosen.append(rng.choice(worlds, size=count, replace=False))
    return np.sort(np.concatenate(chosen)) if chosen else np.zeros(0, dtype=np.int64)


def member_source_set(sources: tuple[str, ...], member: int) -> tuple[str, ...]:
    """The data sources of G_`member` (1-based) in a `member_sources` setting ("+" joins)."""
    if len(sources) != len(MEMBER_NAMES) - 1:
        raise ValueError(
            f"member_sources={','.join(sources)}: give one entry per member "
            f"({len(MEMBER_NAMES) - 1}), sources joined by '+'"
        )
    wanted = tuple(part.strip() for part in sources[member - 1].split("+"))
    unknown = [part for part in wanted if part not in SOURCES]
    if unknown:
        raise ValueError(
            f"member_sources: unknown source(s) {unknown}: choose from {', '.join(SOURCES)}"
        )
    return wanted


def masked_loss(
    logits: torch.Tensor,
    walls: torch.Tensor,
    mask: torch.Tensor,
    wall_weight: float,
    soft_iou_weight: float = 0.0,
    far_soft_iou_weight: float = 0.0,
    far_mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Binary cross-entropy over the masked cells, walls weighted by `wall_weight`, plus
    `soft_iou_weight` times `soft_iou_loss`, plus `far_soft_iou_weight` times the soft IoU
    loss over `far_mask` (the masked cells far from the known ones)."""
    weights = mask * (1.0 + (wall_weight - 1.0) * walls)
    losses = F.binary_cross_entropy_with_logits(logits, walls, reduction="none")
    loss = (losses * weights).sum() / weights.sum().clamp_min(1.0)
    if soft_iou_weight:
        loss = loss + soft_iou_weight * soft_iou_loss(logits, walls, mask)
    if far_soft_iou_weight and far_mask is not None:
        loss = loss + far_soft_iou_weight * soft_iou_loss(logits, walls, far_mask)
    return loss


def far_from_known(inputs: torch.Tensor, mask: torch.Tensor, far_cells: int) -> torch.Tensor:
    """The cells of `mask` more than `far_cells` (Chebyshev) from every known cell of the
    crop, from the one-hot `inputs` (free, occupied, unknown channels)."""
    known = inputs[:, :2].sum(dim=1, keepdim=True).clamp_max(1.0)
    near = F.max_pool2d(known, 2 * far_cells + 1, stride=1, padding=far_cells)
    return mask * (1.0 - near)


def soft_iou_loss(logits: torch.Tensor, walls: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """1 - soft IoU of the wall class over the masked cells, per crop, averaged over the
    batch: the evaluation's metric with probabilities for the thresholded walls. A crop
    with no wall, predicted or true, scores 0 (smoothed by one cell)."""
    predicted, true = torch.sigmoid(logits) * mask, walls * mask
    intersection = (predicted * true).sum((1, 2, 3))
    union = (predicted + true - predicted * true).sum((1, 2, 3))
    return (1.0 - (intersection + 1.0) / (union + 1.0)).mean()


@dataclass(frozen=True)
class _Schedule:
    """One optimisation run: how long, how fast, with what loss, from which batch stream."""

    label: str  # the progress bar's
    steps: int
    learning_rate: float
    wall_weight: float
    soft_iou_weight: float
    seed: int  # of the weights' random draws and of the batch stream
    checkpoint: Path
    sources: tuple[str, ...] = SOURCES  # whose crops it trains on
    far_soft_iou_weight: float = 0.0  # of the soft IoU over the cells far from known ones


def train_member(
    member: int,
    snapshots: SnapshotSet,
    config: PredictorTrainingConfig,
    device: torch.device,
    out_dir: Path,
    resume: bool,
) -> Path:
    """Train one member with checkpoints; write its float16 weights; return their path.
    G's are its base weights (`base_weights`), which `polish_main` turns into g.pt."""
    name = MEMBER_NAMES[member]
    data = member_snapshots(
        snapshots, member, config.member_split, config.member_sources, config.bag_share, config.seed
    )
    schedule = _Schedule(
        label=f"train {name}",
        steps=config.main_steps if member == 0 else config.member_steps,
        learning_rate=config.learning_rate,
        wall_weight=config.wall_weight if member == 0 else config.member_wall_weight,
        soft_iou_weight=0.0,
        seed=config.seed + member,
        checkpoint=out_dir / "checkpoints" / f"{name}.ckpt",
    )
    torch.manual_seed(schedule.seed)
    model = _initial_model(member, config, out_dir).to(device)
    wall_time_s = _fit(model, data, schedule, config, device, resume)
    metadata = _metadata(name, data, config, device) | {
        "steps": schedule.steps,
        "training_wall_time_s": wall_time_s,
    }
    target = base_weights(out_dir) if member == 0 else out_dir / f"{name}.pt"
    return save_weights(target, model, metadata)


def polish_main(
    snapshots: SnapshotSet,
    config: PredictorTrainingConfig,
    device: torch.device,
    out_dir: Path,
    resume: bool,
) -> Path:
    """Fine-tune G's base weights with soft IoU added to its loss; write g.pt.

    Cross-entropy fixes G's walls only up to their operating point; the evaluation
    scores the IoU of the thresholded walls, which the soft IoU term optimises directly.
    With `polish_runs` > 1, G is polished that many times from its base weights, each
    run on its own batch stream, and g.pt is the mean of their weights (a uniform model
    soup): fine-tunes of one start average without leaving its basin, and the mean
    cancels part of each run's noise at no cost at inference. Its members start from
    the base weights, so polishing G changes P_t only."""
    base = base_weights(out_dir)
    polished, wall_time_s = [], 0.0
    for run in range(config.polish_runs):
        schedule = _polish_schedule(config, out_dir, run)
        torch.manual_seed(schedule.seed)
        model = load_member(base).train().to(device)
        wall_time_s += _fit(model, snapshots, schedule, config, device, resume)
        polished.append(model)
    model.load_state_dict(mean_state_dict([m.state_dict() for m in polished]))
    metadata = read_metadata(base) | {
        "polish_steps": config.main_polish_steps,
        "polish_runs": config.polish_runs,
        "polish_soft_iou_weight": config.polish_soft_iou_weight,
        "polish_far_soft_iou_weight": config.polish_far_soft_iou_weight,
        "polish_wall_time_s": round(wall_time_s, 1),
        "polish_training_config": dataclasses.asdict(config),  # may differ from G's base
    }
    return save_weights(_main_weights(out_dir), model, metadata)


def _polish_schedule(config: PredictorTrainingConfig, out_dir: Path, run: int) -> _Schedule:
    """The `run`-th polish of G (0 = the only one when `polish_runs` is 1)."""
    suffix = f"-{run}" if run else ""
    return _Schedule(
        label=f"polish g{suffix}",
        steps=config.main_polish_steps,
        learning_rate=config.polish_learning_rate,
        wall_weight=config.wall_weight,
        soft_iou_weight=config.polish_soft_iou_weight,
        seed=config.seed + len(MEMBER_NAMES) + run,
        checkpoint=out_dir / "checkpoints" / f"g-polish{suffix}.ckpt",
        sources=config.polish_sources,
        far_soft_iou_weight=config.polish_far_soft_iou_weight,
    )


def mean_state_dict(states: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The element-wise mean of networks' floating-point weights (others from the first)."""
    first = states[0]
    return {
        key: torch.stack([state[key] for state in states]).mean(0)
        if value.is_floating_point()
        else value
        for key, value in first.items()
    }


def _fit(
    model: LamaGenerator,
    data: SnapshotSet,
    schedule: _Schedule,
    config: PredictorTrainingConfig,
    device: torch.device,
    resume: bool,
) -> float:
    """Optimise `model` in place (resuming from its checkpoint if asked); return the
    training wall time (s), including that before a resume."""
    if schedule.steps == 0:
        return 0.0
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=schedule.learning_rate, weight_decay=config.weight_decay
    )
    rates = torch.optim.lr_scheduler.OneCycleLR(
        optimizer,
        max_lr=schedule.learning_rate,
        total_steps=schedule.steps,
        pct_start=warmup_fraction(schedule.steps, config.warmup_share),
    )
    start, elapsed = 0, 0.0
    if resume and schedule.checkpoint.exists():
        state = torch.load(schedule.checkpoint, map_location=device, weights_only=False)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        rates.load_state_dict(state["schedule"])
        torch.set_rng_state(state["torch_rng"])
        start, elapsed = state["step"], state["elapsed_s"]
    batches = batch_loader(
        CropSampler(data, config, schedule.sources),
        schedule.seed,
        config.batch_size,
        first_batch=start,
        workers=config.data_workers,
        pin=device.type == "cuda",
    )
    model.train()
    began = time.perf_counter() - elapsed
    steps = schedule.steps
    bar = tqdm(range(start, steps), initial=start, total=steps, desc=schedule.label, unit="step")
    for step, batch in zip(bar, batches, strict=False):  # the batch stream is endless
        inputs, walls, masks = (a.to(device, non_blocking=True) for a in batch)
        with autocast(device, config.precision):
            logits = model(inputs).float()
        far = None
        if schedule.far_soft_iou_weight:
            far = far_from_known(inputs, masks, config.far_cells)
        loss = masked_loss(
            logits, walls, masks, schedule.wall_weight, schedule.soft_iou_weight,
            schedule.far_soft_iou_weight, far,
        )  # fmt: skip
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        rates.step()
        bar.set_postfix(loss=f"{loss.item():.4f}")
        done = step + 1
        if done % config.checkpoint_every_steps == 0 or done == steps:
            _save_checkpoint(schedule.checkpoint, model, optimizer, rates, done, began)
    return round(time.perf_counter() - began, 1)


def warmup_fraction(steps: int, share: float) -> float:
    """OneCycle's warm-up as a fraction of `steps`: `share` of them rounded to whole steps,
    at least two (and fewer than `steps`). torch's OneCycleLR divides by zero when the
    warm-up ends at its first step, as a tenth of a 10-step run would."""
    if steps < 3:
        return share
    return min(max(2, round(share * steps)), steps - 1) / steps


def _metadata(
    name: str, data: SnapshotSet, config: PredictorTrainingConfig, device: torch.device
) -> dict:
    """What a weights file records about its training (besides steps and wall time)."""
    return {
        "member": name,
        "snapshots": len(data.observed),
        "worlds": sorted({data.worlds[i].name for i in np.unique(data.world_of)}),
        "training_config": dataclasses.asdict(config),
        "device": _device_name(device),
    }


def _initial_model(member: int, config: PredictorTrainingConfig, out_dir: Path) -> LamaGenerator:
    """A fresh network; for G_1..G_3 with `members_from_main`, G's trained weights from `out_dir`.

    Starting every member from one trained G, as the paper starts them from one
    pretrained LaMa, makes them differ where their data subsets disagree rather
    than wherever an undertrained network guesses differently."""
    if member == 0 or not config.members_from_main:
        return LamaGenerator(config.network)
    path = base_weights(out_dir)
    main = load_member(path)
    if main.config != config.network:
        raise ValueError(
            f"{path} was built for another network size ({main.config}): "
            "give the same --set network.FIELD=VALUE as when g was trained"
        )
    return main.train()


def _main_weights(out_dir: Path) -> Path:
    """Where G's final (polished) weights are written in `out_dir`."""
    return out_dir / f"{MEMBER_NAMES[0]}.pt"


def base_weights(out_dir: Path) -> Path:
    """Where G's weights before polishing are written in `out_dir`: its members start
    from them."""
    return out_dir / f"{MEMBER_NAMES[0]}-base.pt"


def _save_checkpoint(path, model, optimizer, schedule, step: int, began: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "schedule": schedule.state_dict(),
        "torch_rng": torch.get_rng_state(),
        "step": step,
        "elapsed_s": time.perf_counter() - began,
    }
    staging = path.with_suffix(".tmp")
    torch.save(state, staging)
    staging.replace(path)


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"cpu: {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m mapex.training.train", description=__doc__)
    parser.add_argument("--members", default=",".join(MEMBER_NAMES), help="default: %(default)s")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--out", type=Path, default=WEIGHTS_DIR, help="default: %(default)s")
    parser.add_argument(
        "--kth-dir",
        type=Path,
        default=KTH_DEV_DIR,
        help="folder holding the KTH training maps 50015847 and 50015848 (default: %(default)s)",
    )
    parser.add_argument(
        "--ipa-dir",
        type=Path,
        default=IPA_DIR,
        help="folder holding the IPA training maps (default: %(default)s; --set use_ipa=false "
        "leaves them out)",
    )
    parser.add_argument(
        "--kth-sdf-dir",
        type=Path,
        default=KTH_SDF_DIR / "train",
        help="folder of the kth_sdf training floors <id>.world (default: %(default)s; the "
        "held-out and flagged floors are left out; --set kth_sdf=false leaves all out)",
    )
    parser.add_argument(
        "--snapshots",
        type=Path,
        default=None,
        metavar="FILE.npz",
        help="keep the exploration snapshots here: read when it holds those of this data "
        "setting, written after collecting them otherwise (saves the collection on a rerun)",
    )
    parser.add_argument(
        "--collect-only",
        action="store_true",
        help="collect (and keep) the snapshots, train nothing",
    )
    parser.add_argument(
        "--no-kth",
        action="store_true",
        help="leave the KTH maps out (with --set member_split=thirds or other member_sources)",
    )
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoints")
    parser.add_argument(
        "--calibrate-only",
        action="store_true",
        help="train nothing: choose the decision threshold of the g.pt in --out",
    )
    parser.add_argument(
        "--polish-only",
        action="store_true",
        help="train only G's polish, from the g-base.pt in --out (writes g.pt, then calibrates)",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a training field, e.g. main_steps=500, network.channels=128 or "
        "data_workers=8 (see PredictorTrainingConfig and NetworkConfig in mapex/config.py)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        config = apply_overrides(PredictorTrainingConfig(), args.overrides)
        _check_schedule(config)
        members = [MEMBER_NAMES.index(name) for name in _member_names(args.members)]
        device = _device(args.device)
        if args.threads:
            torch.set_num_threads(args.threads)
        if args.calibrate_only or args.polish_only:
            load_member(_polished_from(args))  # fail before collecting snapshots
            members = []
        _check_main_for_members(members, config, args.out)
        kth_dirs = [] if args.no_kth else [str(args.kth_dir / m) for m in KTH_TRAINING_MAPS]
        if config.kth_sdf and not args.no_kth:
            kth_dirs += kth_sdf_specs(args.kth_sdf_dir)
        ipa_dirs = [str(args.ipa_dir / m) for m in config.ipa_maps] if config.use_ipa else []
        specs = training_world_specs(config, kth_dirs, ipa_dirs)
        _check_enough_worlds(members, len(specs))
        _check_sources(members, config, specs)
        _warn_if_emulated_bfloat16(device, config)
        snapshots = cached_snapshots(args.snapshots, specs, config)
        print(f"{len(snapshots.observed)} snapshots of {len(specs)} worlds", file=sys.stderr)
        if args.collect_only:
            return 0
        for member in members:
            path = train_member(member, snapshots, config, device, args.out, args.resume)
            print(f"wrote {path}")
        polishes = 0 in members or args.polish_only
        if polishes:
            path = polish_main(snapshots, config, device, args.out, args.resume)
            print(f"wrote {path}")
        if args.calibrate_only or (polishes and config.calibrate_main):
            calibration = calibrate_weights(_main_weights(args.out), snapshots, config)
            print(describe(calibration))
    except (ConfigError, WorldError, WeightsError, ValueError) as error:
        print(f"mapex.training.train: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    return 0


def kth_sdf_specs(directory: Path) -> list[str]:
    """World specs of the trainable kth_sdf floors in `directory` (at their real size, the
    converter's frame dropped, as `kth-sdf:ID` loads them), but those that come from the
    authors' rasters in kth_dev; a one-line error when it holds none."""
    floors = [f for f in kth_sdf_training_floors(directory) if f not in KTH_TRAINING_MAPS]
    if not floors:
        raise ValueError(
            f"--kth-sdf-dir {directory}: no trainable <id>.world there (--set kth_sdf=false "
            "trains without them)"
        )
    return [f"{directory / floor}.world@scale={KTH_SDF_SCALE},frame=drop" for floor in floors]


def _warn_if_emulated_bfloat16(device: torch.device, config: PredictorTrainingConfig) -> None:
    if emulated_bfloat16(device, config.precision):
        print(
            "mapex.training.train: warning: this CPU has no native bfloat16, so training in "
            "bfloat16 (the default, which the shipped weights were trained in) runs about ten "
            "times slower than --set precision=float32 (other weights, same quality)",
            file=sys.stderr,
        )


def _check_schedule(config: PredictorTrainingConfig) -> None:
    """Refuse, before any work, step counts and a warm-up that no run can have."""
    if config.polish_runs < 1:
        raise ValueError(f"polish_runs={config.polish_runs}: G needs at least one polish run")
    for field in ("main_steps", "member_steps", "main_polish_steps"):
        if getattr(config, field) < 0:
            raise ValueError(f"{field}={getattr(config, field)}: a step count cannot be negative")
    if not 0.0 < config.warmup_share < 1.0:
        raise ValueError(f"warmup_share={config.warmup_share}: choose a share between 0 and 1")


def _polished_from(args: argparse.Namespace) -> Path:
    """The weights that --calibrate-only (g.pt) or --polish-only (g-base.pt) start from."""
    if args.calibrate_only and args.polish_only:
        raise ValueError("--calibrate-only and --polish-only: give one (--polish-only calibrates)")
    return _main_weights(args.out) if args.calibrate_only else base_weights(args.out)


def _check_main_for_members(members: list[int], config: PredictorTrainingConfig, out: Path) -> None:
    """Refuse, before any work, members that would start from a G this run has not got."""
    main = base_weights(out)
    if config.members_from_main and 0 not in members and not main.exists():
        raise ValueError(
            f"{', '.join(MEMBER_NAMES[k] for k in members)} would start from G's weights, "
            f"but there is no {main}: train g too (--members {','.join(MEMBER_NAMES)}) "
            "or --set members_from_main=false"
        )


def _check_enough_worlds(members: list[int], n_worlds: int) -> None:
    """Refuse, before any work, a run in which a member would get no snapshots at all."""
    needed = 3 if any(member > 0 for member in members) else 1  # G_k: a third of the worlds
    if n_worlds < needed:
        raise ValueError(
            f"{n_worlds} training world(s), but {_names(members)} "
            f"need at least {needed}: raise procedural_worlds or give the KTH maps"
        )


def _check_sources(members: list[int], config: PredictorTrainingConfig, specs: list[str]) -> None:
    """Refuse, before any work, a by-source split in which a member has no data, and a
    polish with no office-like data."""
    present = {world_source(spec_name(spec)) for spec in specs}
    for k in range(1, len(MEMBER_NAMES)):  # a bad setting is an error whatever the split
        member_source_set(config.member_sources, k)
    wanted = [("polish", config.polish_sources)] if 0 in members else []
    if config.member_split == "by_source":
        wanted += [
            (MEMBER_NAMES[k], member_source_set(config.member_sources, k)) for k in members if k
        ]
    for name, sources in wanted:
        if not present & set(sources):
            raise ValueError(
                f"{name} trains on {'+'.join(sources)}, but no training world comes from there "
                f"(have: {', '.join(sorted(present))}): give those maps or other sources"
            )


def _names(members: list[int]) -> str:
    """The members' names for a message ("calibrating g" when none is trained)."""
    return ", ".join(MEMBER_NAMES[k] for k in members) or "calibrating g"


def _member_names(text: str) -> list[str]:
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in MEMBER_NAMES]
    if unknown or not names:
        raise ValueError(f"--members: choose from {', '.join(MEMBER_NAMES)} (got '{text}')")
    return names


def _device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available")
    return torch.device(name)


if __name__ == "__main__":
    sys.exit(main())
