"""A team's state in one process: the shared map, the claim board and the explorers of
the robots decided here (all of them, or one in a robot's planner process).

At each step t every robot sees its teammates' claims and poses as they stood after step
t - 1 and chooses its motion (docs/algorithms.md#teams); the claims made at t are settled
together. A team of one predicts at every re-plan, exactly as a robot alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mapex.config import ExplorationConfig
from mapex.explorer import Explorer
from mapex.grid import Cell, new_observed_map
from mapex.methods import make_method
from mapex.methods.claims import Claim, ClaimBoard
from mapex.methods.teammates import TeamView
from mapex.prediction.base import Predictor
from mapex.sensor import Scan, integrate_scan
from mapex.team.shared_prediction import EpochPrediction, TeammateExplorer


@dataclass(frozen=True)
class Decision:
    """What robot `robot` does at one step: its motion (None: nothing left for it now) and,
    when it re-planned with a coordinating method (`claimed`), its new claim (None: no goal)."""

    robot: int
    motion: np.ndarray | None
    claimed: bool = False
    claim: Claim | None = None


class Team:
    """One shared map, the claim board, and the explorers of the robots decided here (all
    of them in one process; one in a robot's planner process), plus what each robot has
    seen on its own and where each has been."""

    def __init__(
        self,
        shape: tuple[int, int],
        method_name: str,
        predictor: Predictor | None,
        robots: int,
        seed: int,
        config: ExplorationConfig,
        local: Sequence[int],
    ) -> None:
        self.config = config
        self.robots = robots
        self.observed = new_observed_map(shape)
        self.explorers: dict[int, Explorer] = {}
        # a team of one predicts at every re-plan, exactly as a single robot
        epoch_steps = config.team.prediction_epoch_steps if robots > 1 else 1
        self.shared = None if predictor is None else EpochPrediction(
            predictor, epoch_steps, config.sensor.range_cells
        )  # fmt: skip
        for robot in local:
            method = make_method(method_name, config)
            explorer = TeammateExplorer(shape, method, self.shared, config, seed + robot)
            explorer.observed = self.observed  # one map for the whole team
            self.explorers[robot] = explorer
        # the cells each robot's own scans walked, for the overlap
        self.seen = [np.zeros(shape, dtype=bool) for _ in range(robots)]
        self.trajectories: list[list[np.ndarray]] = [[] for _ in range(robots)]
        self.board = ClaimBoard(shape, config.team.claim_conflict_cells)
        self.lost_at: dict[int, int] = {}

    def mark_lost(self, robots: Sequence[int], t: int) -> None:
        """Note the step at which each robot of `robots` was first reported lost."""
        for robot in robots:
            self.lost_at.setdefault(robot, t)

    def poses(self) -> tuple[Cell | None, ...]:
        """Every robot's cell after its last scan (None: a robot reported lost)."""
        return tuple(
            None if robot in self.lost_at or not path else (int(path[-1][0]), int(path[-1][1]))
            for robot, path in enumerate(self.trajectories)
        )

    def decide(self, t: int) -> list[Decision]:
        """The decisions of the robots run here for step t, each seeing the claims and poses
        as they stood after step t - 1."""
        if self.shared is not None:
            self.shared.begin_step(t, self.observed)
        decisions = []
        poses, computed = self.poses(), {}  # what the robots decided here share at this step
        for robot, explorer in self.explorers.items():
            method = explorer.method
            method.teammates = self.board.teammates_of(robot)
            method.team_view = TeamView(robot, t, poses, computed)
            replans = explorer.stats.replans
            motion = explorer.next_motion(t)
            claimed = explorer.stats.replans != replans and method.coordinates
            claim = method.claim_of(robot, t) if claimed else None
            decisions.append(Decision(robot, motion, claimed, claim))
        return decisions

    def settle(self, claims: dict[int, Claim | None]) -> None:
        """Settle the claims made at one step; robots run here that lost theirs re-plan."""
        for robot in self.board.settle(claims):
            if robot in self.explorers:
                self.explorers[robot].goal = self.explorers[robot].path = None

    def observe(self, scans: Sequence[Scan]) -> None:
        """Integrate every robot's scan, in robot order, into the shared map."""
        for robot, scan in enumerate(scans):
            if robot in self.explorers:
                self.explorers[robot].observe(scan, self.seen[robot])
            else:
                integrate_scan(self.observed, scan, self.config.sensor, self.seen[robot])
            self.trajectories[robot].append(np.asarray(scan.pose, dtype=np.int64))

    def overlap(self) -> float:
        counts = np.sum(self.seen, axis=0, dtype=np.int32)
        return float((counts > 1).sum() / max((counts > 0).sum(), 1))
