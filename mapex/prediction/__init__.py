"""Map predictors: observed map in, ensemble of occupancy-probability maps out
(docs/algorithms.md#prediction), and how every command chooses one.

`PREDICTORS` names every predictor by the "module:Class" that implements it, so
that choosing one imports only its own dependencies (the learned ensembles pull
in torch, the classical one OpenCV, the oracle neither). Registering a predictor is one
line. `lama` is the default and means the package's weights folder; `oracle` is the
ground truth itself, an upper bound that is never a default (docs/algorithms.md#the-oracle).
"""

from __future__ import annotations

import argparse
import importlib
from typing import Any

import numpy as np

from mapex.config import ConfigError
from mapex.prediction.base import Predictor
from mapex.prediction.config import DEFAULT_INFERENCE, InferenceConfig
from mapex.prediction.oracle import ORACLE

PREDICTORS: dict[str, str] = {
    "classical": "mapex.prediction.classical:ClassicalInpaintingEnsemble",
    "lama": "mapex.prediction.learned:LearnedEnsemble",
    "lama-v2": "mapex.prediction.learned:LearnedEnsembleV2",
    ORACLE: "mapex.prediction.oracle:OraclePredictor",
}
DEFAULT_PREDICTOR = "lama"
LEARNED_PREDICTORS = ("lama", "lama-v2")  # they run networks: the inference flags are theirs
SERVED_PREDICTORS = (*LEARNED_PREDICTORS, ORACLE)  # what predictor workers serve (services/)

PREDICTOR_HELP = (
    "the map predictor, also used for the IoU/TU metrics: 'lama' (default: the learned "
    "ensemble of the package's weights folder, v3), 'lama-v2' (the v2 ensemble of the "
    "README's validation figures), 'classical' (OpenCV inpainting) or 'oracle' (the ground "
    "truth itself: an upper bound of what a prediction can buy a method, not a predictor a "
    "robot could have; its "
    "runs are labelled @oracle)"
)
# the line every command that runs the oracle logs when it starts
ORACLE_NOTICE = (
    "predictor oracle: the ground truth is the prediction (an upper bound of what a "
    "prediction can buy, not a predictor a robot could have)"
)
IN_PROCESS_ONLY_HELP = "; 'classical' runs in one process only (python -m mapex run)"


def make_predictor(name: str, walls: np.ndarray | None = None, **kwargs: Any) -> Predictor:
    """A new predictor registered as `name`, built with `kwargs` (e.g. a config). `walls`, the
    world's ground truth (`World.occupancy`), is handed to the oracle only, which needs it."""
    if name not in PREDICTORS:
        raise ValueError(
            f"unknown predictor '{name}' (choose from: {', '.join(sorted(PREDICTORS))})"
        )
    if name == ORACLE:
        if walls is None:
            raise ValueError("the oracle predictor needs the world's walls")
        kwargs = {**kwargs, "walls": walls}
    module_name, _, class_name = PREDICTORS[name].partition(":")
    predictor_class = getattr(importlib.import_module(module_name), class_name)
    return predictor_class(**kwargs)


def inference_options(name: str, inference: InferenceConfig) -> dict:
    """The keyword arguments that run predictor `name`'s networks as `inference` says: a
    learned predictor's; for any other a ConfigError (one line) naming the inference flags
    changed from their defaults, since it runs no network."""
    if name in LEARNED_PREDICTORS:
        return inference.ensemble_options()
    given, default = inference.flags(), DEFAULT_INFERENCE.flags()
    changed = [
        f"{flag} {value}"
        for flag, value, usual in zip(given[::2], given[1::2], default[1::2], strict=True)
        if value != usual
    ]
    if changed:
        learned = ", ".join(LEARNED_PREDICTORS)
        raise ConfigError(
            f"{' '.join(changed)}: only the 'lama' predictors ({learned}) run networks"
        )
    return {}


def add_predictor_argument(parser: argparse.ArgumentParser, served: bool = False) -> None:
    """--predictor NAME (default `DEFAULT_PREDICTOR`); `served`: on a command of the
    distributed simulator, whose workers serve `SERVED_PREDICTORS` only
    (`served_predictor_problem`)."""
    parser.add_argument(
        "--predictor",
        default=DEFAULT_PREDICTOR,
        choices=sorted(PREDICTORS),
        help=PREDICTOR_HELP + (IN_PROCESS_ONLY_HELP if served else ""),
    )


def served_predictor_problem(name: str) -> str | None:
    """Why the distributed simulator cannot run predictor `name` (one line), or None."""
    if name in SERVED_PREDICTORS:
        return None
    return (
        f"--predictor {name} runs in one process only (python -m mapex run --predictor {name}); "
        f"the predictor workers serve {', '.join(SERVED_PREDICTORS)}"
    )
