"""Where the learned ensemble's weights live, and how they are written and read.

A weights file holds the float16 state dict of one member, the network size it
was built with and the training metadata (data, steps, device, wall time).
"""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import torch

from mapex.config import NetworkConfig
from mapex.prediction.base import MEMBER_NAMES
from mapex.prediction.network import LamaGenerator

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
_LOAD_ERRORS = (RuntimeError, KeyError, TypeError, ValueError, EOFError, pickle.UnpicklingError)


__all__ = ["MEMBER_NAMES", "WEIGHTS_DIR", "WeightsError", "load_member", "save_weights"]


class WeightsError(ValueError):
    """A weights file that is missing or does not fit the network."""


def save_weights(path: Path, model: LamaGenerator, metadata: dict) -> Path:
    """Write `model` (as float16) with its network size and `metadata`, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {key: value.detach().cpu() for key, value in model.state_dict().items()}
    state = {k: v.half() if v.is_floating_point() else v for k, v in state.items()}
    payload = {
        "state_dict": state,
        "network": dataclasses.asdict(model.config),
        "metadata": metadata,
    }
    staging = path.with_suffix(".tmp")
    torch.save(payload, staging)
    staging.replace(path)
    return path


def load_member(path: Path, device: torch.device | str = "cpu") -> LamaGenerator:
    """The network stored at `path`, in float32 evaluation mode on `device`."""
    if not path.exists():
        raise WeightsError(f"no weights file {path} (train with python -m mapex.prediction.train)")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        model = LamaGenerator(NetworkConfig(**payload["network"]))
        model.load_state_dict({k: v.float() for k, v in payload["state_dict"].items()})
    except _LOAD_ERRORS as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise WeightsError(f"{path}: not a weights file of this network ({reason})") from None
    return model.to(device).eval()


def read_metadata(path: Path) -> dict:
    """The training metadata stored with a weights file."""
    return torch.load(path, map_location="cpu", weights_only=True)["metadata"]
