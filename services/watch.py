"""Kept so `python -m services.watch` still works; the module is services.bridges.watch."""

import sys

from services.bridges.watch import run_cli

if __name__ == "__main__":
    sys.exit(run_cli())
