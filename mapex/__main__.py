"""Entry point of `python -m mapex`."""

import sys

from mapex.cli import main

sys.exit(main())
