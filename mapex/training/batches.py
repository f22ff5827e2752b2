"""Training batches, drawn in the training process or in parallel loader workers.

A GPU trains faster than one process can cut crops, so the crops can be drawn by
`data_workers` loader processes. The order of the batches depends only on the seed and
the number of workers, never on timing: without workers one stream is drawn from
`default_rng(seed)`; with N workers, stream r (r < N) holds batches r, r + N, r + 2N, ...
and the loader takes one batch from each worker in turn. A run resumed at step s first
replays the draws of the batches before s, so it trains on the same batches as an
uninterrupted run.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from mapex.prediction.network import encode_observed
from mapex.training.dataset import CropSampler

Batch = tuple[np.ndarray, np.ndarray, np.ndarray]


def draw_batch(sampler: CropSampler, rng: np.random.Generator, size: int) -> Batch:
    """Inputs float32 (b, 3, c, c), wall targets (b, 1, c, c) and loss masks (b, 1, c, c)."""
    crops = [sampler.sample(rng) for _ in range(size)]
    inputs = np.stack([encode_observed(observed) for observed, _, _ in crops])
    walls = np.stack([w for _, w, _ in crops])[:, None]
    masks = np.stack([m for _, _, m in crops])[:, None]
    return inputs, walls, masks


class CropBatches(IterableDataset):
    """The endless batch stream of one training run, from batch `first_batch` on."""

    def __init__(self, sampler: CropSampler, seed: int, batch_size: int, first_batch: int) -> None:
        self.sampler, self.seed = sampler, seed
        self.batch_size, self.first_batch = batch_size, first_batch

    def __iter__(self):
        rng, replayed = self._stream()
        for _ in range(replayed):
            draw_batch(self.sampler, rng, self.batch_size)
        while True:
            yield tuple(torch.from_numpy(a) for a in draw_batch(self.sampler, rng, self.batch_size))

    def _stream(self) -> tuple[np.random.Generator, int]:
        """This process's random stream and how many of its batches came before `first_batch`.

        The loader asks worker 0 first, so worker i serves stream (i + first_batch) mod N."""
        worker = get_worker_info()
        if worker is None:
            return np.random.default_rng(self.seed), self.first_batch
        stream = (worker.id + self.first_batch) % worker.num_workers
        replayed = len(range(stream, self.first_batch, worker.num_workers))
        return np.random.default_rng([self.seed, stream]), replayed


def batch_loader(
    sampler: CropSampler, seed: int, batch_size: int, first_batch: int, workers: int, pin: bool
) -> DataLoader:
    """Batches from `first_batch` on, drawn by `workers` processes (0: by this one)."""
    return DataLoader(
        CropBatches(sampler, seed, batch_size, first_batch),
        batch_size=None,
        num_workers=workers,
        pin_memory=pin,
        worker_init_fn=_one_thread,
        generator=torch.Generator().manual_seed(seed),  # leaves the global torch RNG alone
    )


def _one_thread(_: int) -> None:
    """Loader workers cut crops with numpy; torch threads there would only compete."""
    torch.set_num_threads(1)
