"""Where the learned ensemble's weights live, and how they are written and read.

A weights file holds the float16 state dict of one member, the network size it
was built with, the training metadata (data, steps, device, wall time) and a logit
bias added to the network's output: 0 for a member as trained, G's decision
threshold once calibrated (`mapex.training.calibration`).
"""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import torch

from mapex.prediction.base import MEMBER_NAMES
from mapex.prediction.config import NetworkConfig
from mapex.prediction.network import LamaGenerator

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
_LOAD_ERRORS = (RuntimeError, KeyError, TypeError, ValueError, EOFError, pickle.UnpicklingError)


__all__ = [
    "MEMBER_NAMES",
    "WEIGHTS_DIR",
    "WeightsError",
    "load_member",
    "load_member_with_bias",
    "read_logit_bias",
    "save_weights",
    "set_logit_bias",
]


class WeightsError(ValueError):
    """A weights file that is missing or does not fit the network."""


def save_weights(path: Path, model: LamaGenerator, metadata: dict, logit_bias: float = 0.0) -> Path:
    """Write `model` (as float16) with its network size, `metadata` and output
    `logit_bias`, atomically."""
    state = {key: value.detach().cpu() for key, value in model.state_dict().items()}
    state = {k: v.half() if v.is_floating_point() else v for k, v in state.items()}
    payload = {
        "state_dict": state,
        "network": dataclasses.asdict(model.config),
        "metadata": metadata,
        "logit_bias": float(logit_bias),
    }
    return _write(path, payload)


def set_logit_bias(path: Path, logit_bias: float, calibration: dict) -> Path:
    """Store `logit_bias` in the weights file at `path`, and `calibration` (how it was
    chosen) in its metadata; the network is left as it is."""
    payload = _read(path)
    payload["logit_bias"] = float(logit_bias)
    payload["metadata"] = {**payload["metadata"], "calibration": calibration}
    return _write(path, payload)


def load_member(path: Path, device: torch.device | str = "cpu") -> LamaGenerator:
    """The network stored at `path`, in float32 evaluation mode on `device`."""
    return load_member_with_bias(path, device)[0]


def load_member_with_bias(
    path: Path, device: torch.device | str = "cpu"
) -> tuple[LamaGenerator, float]:
    """The network stored at `path` (float32, evaluation mode, on `device`) and the bias
    to add to its logits, from one read of the file."""
    payload = _read(path)
    try:
        model = LamaGenerator(NetworkConfig(**payload["network"]))
        model.load_state_dict({k: v.float() for k, v in payload["state_dict"].items()})
    except _LOAD_ERRORS as error:
        raise WeightsError(
            f"{path}: not a weights file of this network ({_first_line(error)})"
        ) from None
    return model.to(device).eval(), _logit_bias(payload)


def read_logit_bias(path: Path) -> float:
    """The bias to add to the logits of the network at `path` (0 in files without one)."""
    return _logit_bias(_read(path))


def _logit_bias(payload: dict) -> float:
    return float(payload.get("logit_bias", 0.0))


def read_metadata(path: Path) -> dict:
    """The training metadata stored with a weights file."""
    return _read(path)["metadata"]


def _read(path: Path) -> dict:
    """The payload of the weights file at `path`."""
    if not path.exists():
        raise WeightsError(f"no weights file {path} (train with python -m mapex.prediction.train)")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except _LOAD_ERRORS as error:
        raise WeightsError(f"{path}: not a weights file ({_first_line(error)})") from None
    if not isinstance(payload, dict):
        raise WeightsError(f"{path}: not a weights file (holds a {type(payload).__name__})")
    return payload


def _write(path: Path, payload: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.with_suffix(".tmp")
    torch.save(payload, staging)
    staging.replace(path)
    return path


def _first_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__
