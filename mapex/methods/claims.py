"""What a robot of a team tells its teammates when it re-plans: its claim.

A claim is the goal a robot drives to, the frontier score that made it choose it, and the
cells it expects to see there. Teammates do not count claimed cells in their own gains
(`mapex_team`) or keep away from claimed goals (`nearest_team`), so the team spreads out. A
claim lasts until the robot's next claim or until it is lost. The claims made at step t are
settled together (`ClaimBoard.settle`) and seen from step t + 1 on, so the outcome never
depends on the order messages arrive in, and a team run is the same in one process and
across processes (docs/algorithms.md#teams).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapex.grid import Cell


@dataclass(frozen=True, eq=False)
class Claim:
    """Robot `robot`'s goal chosen at step `t`: its cell, frontier score and visible set
    (bool (rows, cols), all False for methods that claim only the goal)."""

    robot: int
    t: int
    goal: Cell
    score: float
    visible: np.ndarray


class ClaimBoard:
    """The latest claim of every robot of a team."""

    def __init__(self, shape: tuple[int, int], conflict_cells: float) -> None:
        self.shape = shape
        self.conflict_cells = conflict_cells
        self._claims: dict[int, Claim] = {}

    def settle(self, made: dict[int, Claim | None]) -> list[int]:
        """Post the claims `made` at one step (None: that robot re-planned to no goal), in
        robot order; return the robots that must drop their goal: those whose claim lies
        within `conflict_cells` of a new claim that scores better (their claim is
        withdrawn; they re-plan at their next step)."""
        for robot in sorted(made):
            claim = made[robot]
            if claim is None:
                self.withdraw(robot)
            else:
                self.post(claim)
        losers: set[int] = set()
        for robot in sorted(made):
            claim = made[robot]
            if claim is None:
                continue
            for other in self.teammates_of(robot):
                if other.robot not in losers and self._beaten(other, claim):
                    losers.add(other.robot)
        for robot in losers:
            self.withdraw(robot)
        return sorted(losers)

    def _beaten(self, held: Claim, new: Claim) -> bool:
        gap = float(np.hypot(held.goal[0] - new.goal[0], held.goal[1] - new.goal[1]))
        return gap <= self.conflict_cells and new.score > held.score

    def post(self, claim: Claim) -> None:
        """Make `claim` its robot's claim (replacing the older one)."""
        self._claims[claim.robot] = claim

    def withdraw(self, robot: int) -> None:
        """Forget `robot`'s claim (it ended or is lost)."""
        self._claims.pop(robot, None)

    def of(self, robot: int) -> Claim | None:
        return self._claims.get(robot)

    def teammates_of(self, robot: int) -> list[Claim]:
        """The claims of every other robot, in robot order."""
        return [self._claims[k] for k in sorted(self._claims) if k != robot]

    def claimed_by_teammates(self, robot: int) -> np.ndarray:
        """bool (rows, cols): the union of the other robots' visible sets."""
        return claimed_cells(self.teammates_of(robot), self.shape)


def claimed_cells(claims: list[Claim], shape: tuple[int, int]) -> np.ndarray:
    """bool (rows, cols): the union of the visible sets of `claims`."""
    claimed = np.zeros(shape, dtype=bool)
    for claim in claims:
        claimed |= claim.visible
    return claimed
