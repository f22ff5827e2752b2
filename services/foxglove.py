"""Kept beside `python -m services.web`: `python -m services.foxglove` runs the live Foxglove
server of services.bridges.foxglove_live."""

import sys

from services.bridges.foxglove_live import run_cli

if __name__ == "__main__":
    sys.exit(run_cli())
