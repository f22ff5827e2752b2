"""`python -m mapex.worlds`: render a world as a PNG to look at it (a procedural plan, a
Gazebo world as converted, any world spec), or list the validation worlds' specs."""

import argparse
import sys
from pathlib import Path

import numpy as np

from mapex.config import argparse_type, parse_seed
from mapex.exit_codes import EXIT_USAGE
from mapex.worlds.base import World, WorldError
from mapex.worlds.data import kth_validation_specs, validation_map_dirs
from mapex.worlds.procedural import generate_floor_plan, plan_config
from mapex.worlds.sources import load_world, world_spec_help

LISTS = {
    "validation": lambda: [str(path) for path in validation_map_dirs()],
    "kth-validation": kth_validation_specs,
}


def main(argv: list[str] | None = None) -> int:
    """Save one world as a PNG (walls black, valid space light blue), or print a list of
    world specs, one per line (e.g. `--maps $(python -m mapex.worlds --list kth-validation)`)."""
    parser = argparse.ArgumentParser(
        prog="python -m mapex.worlds",
        description="Render a world (default: a procedural floor plan) as a PNG, or list the "
        "specs of the validation worlds.",
    )
    parser.add_argument(
        "--seed", type=argparse_type(parse_seed), default=0, help="plan seed (default: 0)"
    )
    parser.add_argument(
        "--free-outside", action="store_true", help="free space around the building, as in KTH"
    )
    parser.add_argument(
        "--world", default=None, help=f"render this world instead: {world_spec_help()}"
    )
    parser.add_argument("--out", type=Path, default=Path("plan.png"), help="PNG to write")
    parser.add_argument(
        "--list",
        choices=sorted(LISTS),
        default=None,
        help="print the specs of the six validation maps or of the 18 KTH validation floors",
    )
    args = parser.parse_args(argv)
    if args.list:
        try:
            print("\n".join(LISTS[args.list]()))
        except BrokenPipeError:  # `| head`: the reader has what it wanted
            sys.stderr.close()
        return 0
    try:
        world = (
            load_world(args.world)
            if args.world
            else generate_floor_plan(args.seed, plan_config(args.free_outside))
        )
    except WorldError as error:
        print(f"python -m mapex.worlds: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    save_png(world, args.out)
    valid_m2 = int(world.valid_space.sum()) * world.resolution_m**2
    rows, cols = world.shape
    print(f"{world.name}: {rows} x {cols} cells, {valid_m2:.0f} m^2 valid -> {args.out}")
    return 0


def save_png(world: World, path: Path) -> None:
    """Walls black, valid space light blue, the rest white; one pixel per cell."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    image = np.ones((*world.shape, 3))
    image[world.valid_space] = (0.8, 0.9, 1.0)
    image[world.occupancy] = 0.0
    plt.imsave(path, image)


if __name__ == "__main__":
    sys.exit(main())
