"""Kept so `python -m services.ros2` still works; the module is services.bridges.ros2."""

import sys

from services.bridges.ros2 import run_cli

if __name__ == "__main__":
    sys.exit(run_cli())
