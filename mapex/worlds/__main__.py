"""`python -m mapex.worlds`: render one procedural floor plan as a PNG, to look at it."""

import argparse
import sys
from pathlib import Path

import numpy as np

from mapex.config import argparse_type, parse_seed
from mapex.worlds.procedural import generate_floor_plan, plan_config


def main(argv: list[str] | None = None) -> int:
    """Save one plan as a PNG: walls black, valid space light blue."""
    parser = argparse.ArgumentParser(
        prog="python -m mapex.worlds", description="Render one procedural floor plan."
    )
    parser.add_argument(
        "--seed", type=argparse_type(parse_seed), default=0, help="plan seed (default: 0)"
    )
    parser.add_argument("--out", type=Path, default=Path("plan.png"), help="PNG to write")
    parser.add_argument(
        "--free-outside", action="store_true", help="free space around the building, as in KTH"
    )
    args = parser.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    world = generate_floor_plan(args.seed, plan_config(args.free_outside))
    image = np.ones((*world.shape, 3))
    image[world.valid_space] = (0.8, 0.9, 1.0)
    image[world.occupancy] = 0.0
    plt.imsave(args.out, image)
    print(f"{world.name}: {world.shape[0]} x {world.shape[1]} cells -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
