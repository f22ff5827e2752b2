"""Stored digests of whole episodes: trajectories, curves, AUCs and the final map of runs
chosen across methods, worlds, starts and team sizes stay bit-identical through
refactoring (recorded before the single-robot and team loops became one, issue #52).

A deliberate change of behaviour updates a digest here, with the reason in its commit.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import pytest

from mapex.config import ExplorationConfig
from mapex.episode import EpisodeResult, run_episode
from mapex.prediction import make_predictor
from mapex.worlds import StartSpec, load_world


@dataclass(frozen=True)
class Case:
    """One stored episode: method, world spec, predictor, robots, start, seed, steps."""

    method: str
    world: str
    predictor: str | None
    robots: int
    start: StartSpec
    seed: int
    steps: int
    until_iou: float | None = None


CASES: dict[Case, str] = {
    Case("mapex", "generated:3", "classical", 1, 0, 0, 400): "eee352543276600d",
    Case("upen", "generated:5", "classical", 1, 1, 4, 150): "c6006d5ebe79ecdc",
    Case("nearest", "default", None, 1, 2, 0, 250): "9f7b55270892bb71",
    Case("mapex_plus", "generated:0", "classical", 1, 3, 1, 150): "6c9e07e34f7870ff",
    Case("pipe", "default", "lama-v2", 1, 1, 2, 60): "0a10284cf4245fe2",  # v2: fixed weights
    Case("ig_hector", "generated:7", "classical", 1, (40, 40), 0, 150): "e93efb41965c49e4",
    Case("nearest", "generated:2", None, 1, 0, 0, 800, until_iou=0.5): "e1fa0cf2e571ed5e",
    Case("mapex_team", "generated:5", "classical", 3, 1, 7, 120): "4c24465b3f3e4ba8",
    Case("nearest_team", "generated:3", None, 3, 0, 3, 1500): "0dff3538c4f1a924",
    Case("nearest", "generated:3", None, 1, 1, 0, 1500): "ecf5b518407db99e",
    Case("mapex_independent", "generated:5", "classical", 2, 2, 5, 100): "637aae1582597142",
}


def run_case(case: Case) -> EpisodeResult:
    """The episode `case` describes, in one process."""
    world = load_world(case.world)
    predictor = None if case.predictor is None else make_predictor(case.predictor)
    config = ExplorationConfig(steps=case.steps, until_iou=case.until_iou)
    return run_episode(
        world, case.method, predictor, case.start, case.seed, config, robots=case.robots
    )


def digest(result: EpisodeResult) -> str:
    """sha256 of every robot's trajectory, the curves, AUCs, end and final observed map."""
    hasher = hashlib.sha256()
    for path in result.trajectories:
        hasher.update(np.ascontiguousarray(path, dtype=np.int64).tobytes())
    curves = result.curves
    for values in (curves.steps, curves.coverage, curves.iou, curves.tu):
        hasher.update(repr([round(float(v), 12) for v in values]).encode())
    hasher.update(repr({k: round(v, 12) for k, v in curves.auc().items()}).encode())
    hasher.update(repr((result.finished_at, result.end_reason)).encode())
    hasher.update(np.ascontiguousarray(result.final_observed).tobytes())
    return hasher.hexdigest()[:16]


@pytest.mark.parametrize("case", list(CASES), ids=lambda c: f"{c.method}-{c.world}-{c.robots}")
def test_episode_digest_is_unchanged(case: Case) -> None:
    assert digest(run_case(case)) == CASES[case]
