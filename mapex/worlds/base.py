"""The ground-truth world every other module explores."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapex.grid import RESOLUTION_M

GENERATED_PREFIX = "generated:"  # world names of procedural floor plans
OPEN_GENERATED_PREFIX = "generated-open:"  # the same plans with free space outside
HOUSE_PREFIX = "houseexpo:"  # one HouseExpo house
CORRIDOR_PREFIX = "houseexpo-corridor:"  # HouseExpo houses along a corridor
KTH_SDF_PREFIX = "kth-sdf:"  # a KTH floor of the shared data's Gazebo worlds


def generated_prefix(free_outside: bool) -> str:
    """The world-name prefix of procedural plans with free space outside or solid wall."""
    return OPEN_GENERATED_PREFIX if free_outside else GENERATED_PREFIX


class WorldError(ValueError):
    """A world that cannot be loaded or generated; the message is one line naming the cause."""


def parse_seed(text: str, what: str = "generated seed") -> int:
    """The non-negative integer of a world spec's argument; a one-line WorldError naming
    `what` otherwise."""
    if not (text.isascii() and text.isdigit()):
        raise WorldError(f"bad {what} '{text}': expected a non-negative integer")
    return int(text)


def one_line(error: BaseException) -> str:
    """An exception's message on one line (its type's name if it has none), for WorldError."""
    return " ".join(str(error).split()) or type(error).__name__


@dataclass(frozen=True)
class World:
    """A floor plan at 0.1 m per cell.

    occupancy: bool (rows, cols), True = wall.
    valid_space: bool (rows, cols), True = inside a room of the building
    (docs/algorithms.md#worlds).
    """

    name: str
    occupancy: np.ndarray
    valid_space: np.ndarray
    resolution_m: float = RESOLUTION_M

    def __post_init__(self) -> None:
        if self.occupancy.shape != self.valid_space.shape or self.occupancy.ndim != 2:
            raise WorldError(
                f"world '{self.name}': occupancy {self.occupancy.shape} and valid space "
                f"{self.valid_space.shape} must be 2-D maps of the same shape"
            )

    def check_size(self, max_cells: int) -> World:
        """This world, or a one-line WorldError when it has more than `max_cells` cells (the
        `world.max_cells` setting), naming the `--set` that raises the limit."""
        cells = self.occupancy.size
        if cells > max_cells:
            rows, cols = self.shape
            raise WorldError(
                f"world '{self.name}' has {cells:,} cells ({rows} x {cols}), above the limit of "
                f"{max_cells:,}: predictions on it would time out; raise the limit with "
                f"--set world.max_cells={cells} if the predictors are fast enough"
            )
        return self

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupancy.shape  # type: ignore[return-value]
