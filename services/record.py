"""Kept so `python -m services.record` still works; the module is services.bridges.record."""

import sys

from services.bridges.record import run_cli

if __name__ == "__main__":
    sys.exit(run_cli())
