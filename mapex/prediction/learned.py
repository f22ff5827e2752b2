"""The learned ensemble: G and G_1..G_3, LaMa-style generators trained by this project.

The weights ship in `mapex/prediction/weights/` (made by `python -m mapex.training.train`;
`--predictor lama`), and the v2 ensemble stays in `weights/v2/` (`--predictor lama-v2`,
`LearnedEnsembleV2`) whatever the default folder holds; they load on CPU with no GPU
present and use a GPU when asked. A member's stored logit bias (G's calibrated decision
threshold, 0 for G_1..G_3) is added to its output. Torch runs with
`threads` CPU threads (all cores when alone on the machine, one per worker when several
share it); an `InferenceConfig` says how the networks run (docs/benchmarks.md#the-predictor).
The last few answers are kept by crop digest, so the same crop asked twice (G's metric
prediction and a re-plan's on the same map, or the planners of a team) costs one pass.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from mapex.prediction.base import Predictor
from mapex.prediction.config import InferenceConfig, NetworkConfig
from mapex.prediction.inference import FusedGenerator
from mapex.prediction.network import autocast, encode_observed
from mapex.prediction.recent import RECENT_ANSWERS, RecentAnswers, crop_digest
from mapex.prediction.weights import MEMBER_NAMES, WEIGHTS_DIR, load_member_with_bias


class LearnedEnsemble(Predictor):
    """Four trained generators; member 0 is G."""

    name = "lama"
    context_cells = NetworkConfig().context_cells
    default_weights_dir = WEIGHTS_DIR  # where `<member>.pt` are read without a weights_dir

    def __init__(
        self,
        weights_dir: Path | None = None,
        device: str = "cpu",
        threads: int | None = None,
        members: Sequence[str] = MEMBER_NAMES,
        precision: str = "float32",
        inference: str = "fused",
        views: int = 2,
        recent_answers: int = RECENT_ANSWERS,
    ) -> None:
        self.inference = InferenceConfig(precision, inference, views)  # ValueError if bad
        if threads is not None:
            torch.set_num_threads(threads)
        self.device = torch.device(device)
        folder = Path(self.default_weights_dir if weights_dir is None else weights_dir)
        loaded = [load_member_with_bias(folder / f"{name}.pt", self.device) for name in members]
        self.models = [self._runnable(model) for model, _ in loaded]
        self.logit_biases = [bias for _, bias in loaded]
        self.n_members = len(self.models)
        self.recent = RecentAnswers(recent_answers) if recent_answers > 0 else None

    def _runnable(self, model: torch.nn.Module) -> torch.nn.Module:
        """`model` as `self.inference` runs it: fused or plain, with its number of views
        (which overrides the weights file's `average_turned_view`, the training default)."""
        model.config = _with_views(model.config, self.inference.views)
        if self.inference.path == "fused":
            return FusedGenerator(model).to(self.device)
        return model

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """Wall probabilities float32 (len(members), rows, cols) of the chosen members."""
        if observed.size == 0:
            return np.zeros((len(members), *observed.shape), dtype=np.float32)
        if self.recent is None:
            return np.stack([self._run(observed, k) for k in members])
        digest = crop_digest(observed)
        return np.stack(
            [
                self.recent.get_or_compute((digest, k), lambda k=k: self._run(observed, k))
                for k in members
            ]
        )

    def _run(self, observed: np.ndarray, member: int) -> np.ndarray:
        """One member's wall probabilities on `observed`: its network's forward pass(es)."""
        if self.inference.path == "fused":
            # codes; a read-only array (a decoded message's) is copied for torch
            inputs = torch.from_numpy(np.require(observed, np.uint8, ["C", "W"]))[None]
        else:
            inputs = torch.from_numpy(encode_observed(observed))[None]  # one-hot image
        inputs = inputs.to(self.device)
        with torch.inference_mode(), autocast(self.device, self.inference.precision):
            logits = self.models[member].predict_logits(inputs)[0, 0].float()
            return torch.sigmoid(logits + self.logit_biases[member]).cpu().numpy()


class LearnedEnsembleV2(LearnedEnsemble):
    """The v2 ensemble (the README's and docs/results' figures), read from `weights/v2/`, so
    that it can be chosen by name once the default folder holds newer weights."""

    name = "lama-v2"
    default_weights_dir = WEIGHTS_DIR / "v2"


def _with_views(config: NetworkConfig, views: int) -> NetworkConfig:
    """`config` computing `views` views (1: the map, 2: and its 180-degree turn)."""
    return dataclasses.replace(config, average_turned_view=views == 2)
