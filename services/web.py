"""Kept so `python -m services.web` still works; the module is services.bridges.web."""

import sys

from services.bridges.web import run_cli

if __name__ == "__main__":
    sys.exit(run_cli())
