"""Map predictors: observed map in, ensemble of occupancy-probability maps out
(docs/algorithms.md#prediction).

`PREDICTORS` names every predictor by the "module:Class" that implements it, so
that choosing one imports only its own dependencies (the learned ensemble pulls
in torch, the classical one does not). Registering a predictor is one line.
"""

from __future__ import annotations

import importlib
from typing import Any

from mapex.prediction.base import Predictor

PREDICTORS: dict[str, str] = {
    "classical": "mapex.prediction.classical:ClassicalInpaintingEnsemble",
    "lama": "mapex.prediction.learned:LearnedEnsemble",
}
DEFAULT_PREDICTOR = "lama"


def make_predictor(name: str, **kwargs: Any) -> Predictor:
    """A new predictor registered as `name`, built with `kwargs` (e.g. a config)."""
    if name not in PREDICTORS:
        raise ValueError(
            f"unknown predictor '{name}' (choose from: {', '.join(sorted(PREDICTORS))})"
        )
    module_name, _, class_name = PREDICTORS[name].partition(":")
    predictor_class = getattr(importlib.import_module(module_name), class_name)
    return predictor_class(**kwargs)
