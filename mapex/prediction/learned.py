"""The learned ensemble: G and G_1..G_3, LaMa-style generators trained by this project.

The weights ship in `mapex/prediction/weights/` (made by `python -m
mapex.prediction.train`); they load on CPU with no GPU present and use a GPU when
asked. A member's stored logit bias is added to its output: G's calibrated decision
threshold (`mapex.prediction.calibration`), 0 for G_1..G_3. Torch runs with
`threads` CPU threads (all cores when alone on the machine, one per worker when
several share it). With `precision="bfloat16"` the forward pass runs under bfloat16
autocast: about twice as fast on CPUs with AVX512-BF16 or AMX and on GPUs (slower on
CPUs without them); probabilities move by at most about 0.01. float32 is the default,
with which every figure in the README was measured.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from mapex.prediction.base import Predictor
from mapex.prediction.config import PRECISIONS, NetworkConfig, Precision
from mapex.prediction.network import autocast, encode_observed
from mapex.prediction.weights import MEMBER_NAMES, WEIGHTS_DIR, load_member_with_bias


class LearnedEnsemble(Predictor):
    """Four trained generators; member 0 is G."""

    name = "lama"
    context_cells = NetworkConfig().context_cells

    def __init__(
        self,
        weights_dir: Path = WEIGHTS_DIR,
        device: str = "cpu",
        threads: int | None = None,
        members: Sequence[str] = MEMBER_NAMES,
        precision: Precision = "float32",
    ) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision {precision!r}: choose from {', '.join(PRECISIONS)}")
        self.precision = precision
        if threads is not None:
            torch.set_num_threads(threads)
        self.device = torch.device(device)
        loaded = [
            load_member_with_bias(Path(weights_dir) / f"{name}.pt", self.device) for name in members
        ]
        self.models = [model for model, _ in loaded]
        self.logit_biases = [bias for _, bias in loaded]
        self.n_members = len(self.models)

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """Wall probabilities float32 (len(members), rows, cols) of the chosen members."""
        if observed.size == 0:
            return np.zeros((len(members), *observed.shape), dtype=np.float32)
        inputs = torch.from_numpy(encode_observed(observed))[None].to(self.device)
        with torch.inference_mode(), autocast(self.device, self.precision):
            logits = [self.models[k].predict_logits(inputs)[0, 0].float() for k in members]
            outputs = [
                torch.sigmoid(z + self.logit_biases[k])
                for z, k in zip(logits, members, strict=True)
            ]
        return torch.stack(outputs).cpu().numpy()
