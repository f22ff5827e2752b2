"""Training data for the map predictor: observation snapshots paired with ground truth.

Snapshots are what the predictor sees in use: observed maps O_t taken while the
exploration core explores a world (several methods and start poses, many time
steps). Training samples are random crops of them, centred near frontiers most of
the time, with flips and 90-degree rotations.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mapex.config import ExplorationConfig, MetricsConfig
from mapex.explorer import Explorer
from mapex.frontiers import frontier_cells
from mapex.grid import UNKNOWN
from mapex.methods import make_method
from mapex.metrics import building_footprint
from mapex.prediction.config import PredictorTrainingConfig
from mapex.prediction.network import OUTSIDE_MAP
from mapex.simulator import Simulator
from mapex.worlds import World, generated_prefix, load_world, start_poses
from mapex.worlds.base import CORRIDOR_PREFIX, KTH_SDF_PREFIX
from mapex.worlds.data import SOURCES, never_train_on, world_source
from mapex.worlds.gazebo import SUFFIXES as GAZEBO_SUFFIXES


@dataclass
class SnapshotSet:
    """Snapshots of explorations: `observed[i]` was taken in world `world_of[i]`."""

    worlds: list[World]
    observed: list[np.ndarray]
    world_of: np.ndarray  # int (n,)

    def subset(self, keep: np.ndarray) -> SnapshotSet:
        """The snapshots where `keep` (bool (n,)) is True."""
        indices = np.flatnonzero(keep)
        return SnapshotSet(self.worlds, [self.observed[i] for i in indices], self.world_of[indices])


def training_world_specs(
    config: PredictorTrainingConfig, kth_dirs: list[str], ipa_dirs: list[str] = ()
) -> list[str]:
    """World specs to explore: procedural plans, HouseExpo corridor worlds, then the KTH and
    IPA map directories given (a validation map among them is refused)."""
    for directory in [*kth_dirs, *ipa_dirs]:
        check_trainable(spec_name(directory))
    first = config.first_procedural_seed
    prefix = generated_prefix(config.free_outside_plans)
    procedural = [f"{prefix}{seed}" for seed in range(first, first + config.procedural_worlds)]
    first = config.first_houseexpo_seed
    houseexpo = [
        f"{CORRIDOR_PREFIX}{seed}" for seed in range(first, first + config.houseexpo_worlds)
    ]
    return procedural + houseexpo + list(kth_dirs) + list(ipa_dirs)


def spec_name(spec: str) -> str:
    """The name a world spec's world will have (a map directory's or an SDF file's own
    name, a kth_sdf floor's id)."""
    if spec.startswith(KTH_SDF_PREFIX):
        return spec[len(KTH_SDF_PREFIX) :]
    path = spec.partition("@")[0]
    if path.lower().endswith(GAZEBO_SUFFIXES):
        return Path(path).stem
    return os.path.basename(os.path.normpath(spec))


def check_trainable(world_name: str) -> None:
    """Refuse (ValueError) a validation map, or another rendering of its building."""
    if never_train_on(world_name):
        raise ValueError(f"{world_name} is a validation map (mapex.worlds.data): never train on it")


def snapshots_at(
    world: World, method: str, start: tuple[int, int], times: list[int], seed: int = 0
) -> tuple[dict[int, np.ndarray], int | None]:
    """Observed maps O_t at each step t in `times` of one exploration, and the step at which
    it ended early (None if it did not). After an early end the map no longer changes, so
    later times get the final map."""
    exploration = ExplorationConfig()
    simulator = Simulator(world, [start], exploration.sensor, exploration.motion)
    explorer = Explorer(world.shape, make_method(method, exploration), None, exploration, seed)
    explorer.observe(simulator.scan(0))
    wanted, snapshots, finished_at = set(times), {}, None
    for t in range(max(times) + 1):
        if t in wanted:
            snapshots[t] = explorer.observed.copy()
        motion = explorer.next_motion(t) if finished_at is None else None
        if motion is None:
            finished_at = t if finished_at is None else finished_at
            continue
        explorer.observe(simulator.step(0, motion))
    return snapshots, finished_at


def explore_snapshots(spec: str, config: PredictorTrainingConfig) -> list[np.ndarray]:
    """Observed maps every `snapshot_every_steps` steps of explorations of world `spec`
    (until an exploration ends, so no map is repeated)."""
    check_trainable(spec_name(spec))
    world = load_world(spec)
    starts = start_poses(world, ExplorationConfig().world.start_clearance_cells)
    n_starts = starts_per_world(world.name, config)
    every = config.snapshot_every_steps
    times = list(range(every // 2, config.snapshot_steps, every))
    collected = []
    for run, (method, start) in enumerate(
        (m, s) for m in config.snapshot_methods for s in starts[:n_starts]
    ):
        snapshots, finished_at = snapshots_at(world, method, start, times, seed=run)
        end = config.snapshot_steps if finished_at is None else finished_at
        collected += [snapshots[t] for t in times if t <= end]
    return collected


def starts_per_world(world_name: str, config: PredictorTrainingConfig) -> int:
    """How many start corners to explore a training world from (by its source)."""
    return {
        "kth": config.kth_starts_per_world,
        "ipa": config.ipa_starts_per_world,
    }.get(world_source(world_name), config.starts_per_world)


def collect_snapshots(
    specs: list[str], config: PredictorTrainingConfig, processes: int | None = None
) -> SnapshotSet:
    """Explore every world (in `processes` spawned processes, default one per CPU core) and
    gather the snapshots, in the order of `specs` whatever the number of processes."""
    context = multiprocessing.get_context("spawn")
    with context.Pool(processes or os.cpu_count()) as pool:
        jobs = pool.imap(_explore, [(spec, config) for spec in specs])
        per_world = list(tqdm(jobs, total=len(specs), desc="snapshots", unit="world"))
    worlds = [load_world(spec) for spec in specs]
    return _snapshot_set(worlds, per_world)


def _explore(job: tuple[str, PredictorTrainingConfig]) -> list[np.ndarray]:
    return explore_snapshots(*job)


def _snapshot_set(worlds: list[World], per_world: list[list[np.ndarray]]) -> SnapshotSet:
    observed = [snapshot for snapshots in per_world for snapshot in snapshots]
    world_of = np.concatenate(
        [np.full(len(snapshots), i, dtype=np.int64) for i, snapshots in enumerate(per_world)]
    )
    return SnapshotSet(worlds, observed, world_of)


def snapshot_key(specs: list[str], config: PredictorTrainingConfig) -> str:
    """What a set of snapshots depends on: the worlds and the exploration settings."""
    fields = ("snapshot_methods", "starts_per_world", "ipa_starts_per_world",
              "kth_starts_per_world", "snapshot_steps", "snapshot_every_steps")  # fmt: skip
    settings = {name: getattr(config, name) for name in fields}
    return json.dumps({"specs": specs, "settings": settings}, sort_keys=True, default=list)


def cached_snapshots(
    path: Path | None, specs: list[str], config: PredictorTrainingConfig
) -> SnapshotSet:
    """The snapshots of `specs`: read from the file at `path` when it holds exactly those,
    else collected (and written there, when a path is given)."""
    key = snapshot_key(specs, config)
    if path is not None and path.is_file():
        with np.load(path) as stored:
            if str(stored["key"]) == key:
                print(f"snapshots read from {path}", file=sys.stderr)
                flat, shapes, counts = stored["maps"], stored["shapes"], stored["counts"]
                ends = np.cumsum([rows * cols for rows, cols in shapes])
                maps = [
                    m.reshape(s) for m, s in zip(np.split(flat, ends[:-1]), shapes, strict=True)
                ]
                per_world = np.split(np.arange(len(maps)), np.cumsum(counts)[:-1])
                worlds = [load_world(spec) for spec in specs]
                return _snapshot_set(worlds, [[maps[i] for i in idx] for idx in per_world])
            print(f"{path} holds other snapshots: collecting again", file=sys.stderr)
    snapshots = collect_snapshots(specs, config)
    if path is not None:
        counts = np.bincount(snapshots.world_of, minlength=len(specs))
        shapes = np.array([m.shape for m in snapshots.observed], dtype=np.int64)
        flat = np.concatenate([m.ravel() for m in snapshots.observed])
        path.parent.mkdir(parents=True, exist_ok=True)
        staging = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(staging, key=key, maps=flat, shapes=shapes, counts=counts)
        staging.replace(path)
    return snapshots


class CropSampler:
    """Random training crops (input one-hot source, target walls, loss mask) from snapshots."""

    def __init__(
        self,
        snapshots: SnapshotSet,
        config: PredictorTrainingConfig,
        sources: tuple[str, ...] = SOURCES,
    ) -> None:
        self.snapshots = snapshots
        self.crop = config.crop_cells
        self.overhang = config.edge_overhang_cells
        self.frontier_share = config.frontier_share
        self.probabilities = snapshot_probabilities(snapshots, source_shares(config, sources))
        margin = MetricsConfig().footprint_margin_cells
        self.footprints = [building_footprint(w.valid_space, margin) for w in snapshots.worlds]

    def sample(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One crop: observed codes (c, c) uint8, walls (c, c) float32, loss mask (c, c) float32.

        The loss covers unknown cells inside the building footprint. A crop may hang over
        the map's border by up to `edge_overhang_cells`: cells beyond it are `OUTSIDE_MAP`
        and outside the loss.
        """
        index = int(rng.choice(len(self.snapshots.observed), p=self.probabilities))
        observed = self.snapshots.observed[index]
        world_index = int(self.snapshots.world_of[index])
        world = self.snapshots.worlds[world_index]
        row, col = self._centre(observed, rng)
        window = self._window(observed.shape, row, col)
        crop_observed = self._cut(observed, window, OUTSIDE_MAP)
        walls = self._cut(world.occupancy, window, False).astype(np.float32)
        inside = self._cut(self.footprints[world_index], window, False)
        mask = (inside & (crop_observed == UNKNOWN)).astype(np.float32)
        return augment(rng, crop_observed, walls, mask)

    def _centre(self, observed: np.ndarray, rng: np.random.Generator) -> tuple[int, int]:
        """A frontier cell (jittered by up to a quarter crop) or, sometimes, any cell."""
        if rng.random() < self.frontier_share:
            cells = np.argwhere(frontier_cells(observed))
            if len(cells):
                jitter = rng.integers(-self.crop // 4, self.crop // 4 + 1, size=2)
                row, col = cells[rng.integers(len(cells))] + jitter
                return int(row), int(col)
        return int(rng.integers(observed.shape[0])), int(rng.integers(observed.shape[1]))

    def _window(self, shape: tuple[int, int], row: int, col: int) -> tuple[int, int]:
        """Top-left corner of a crop around (row, col), over the map's border by at most
        `overhang` cells (a map smaller than the crop lies wholly inside it)."""
        half, crop, over = self.crop // 2, self.crop, self.overhang
        top = int(
            np.clip(row - half, min(0, shape[0] - crop) - over, max(shape[0] - crop, 0) + over)
        )
        left = int(
            np.clip(col - half, min(0, shape[1] - crop) - over, max(shape[1] - crop, 0) + over)
        )
        return top, left

    def _cut(self, array: np.ndarray, corner: tuple[int, int], fill) -> np.ndarray:
        out = np.full((self.crop, self.crop), fill, dtype=array.dtype)
        top, left = corner
        r0, c0 = max(top, 0), max(left, 0)
        r1, c1 = min(top + self.crop, array.shape[0]), min(left + self.crop, array.shape[1])
        out[r0 - top : r1 - top, c0 - left : c1 - left] = array[r0:r1, c0:c1]
        return out


def source_shares(config: PredictorTrainingConfig, sources: tuple[str, ...] = SOURCES) -> dict:
    """The crop share of each of `sources` (the others get none), from `config`."""
    unknown = sorted(set(sources) - set(SOURCES))
    if unknown:
        raise ValueError(f"unknown data source(s) {unknown}: choose from {', '.join(SOURCES)}")
    return {
        source: getattr(config, f"{source}_share") if source in sources else 0.0
        for source in SOURCES
    }


def snapshot_probabilities(snapshots: SnapshotSet, shares: dict[str, float]) -> np.ndarray:
    """Sampling probability per snapshot: each source present gets its share (renormalised
    over the sources present), split evenly between its snapshots."""
    source_of_world = np.array([world_source(world.name) for world in snapshots.worlds])
    source = source_of_world[snapshots.world_of]
    weights = np.zeros(len(source))
    for name, share in shares.items():
        here = source == name
        if here.any() and share > 0:
            weights[here] = share / here.sum()
    if weights.sum() <= 0:
        present = ", ".join(sorted(set(source.tolist())))
        raise ValueError(
            f"no training snapshot from a source with a positive share (have: {present})"
        )
    return weights / weights.sum()


def augment(rng: np.random.Generator, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The same random flip and 90-degree rotation applied to every array."""
    turns = int(rng.integers(4))
    flip = bool(rng.integers(2))
    out = []
    for array in arrays:
        array = np.rot90(array, turns)
        out.append(np.ascontiguousarray(array[:, ::-1] if flip else array))
    return tuple(out)
