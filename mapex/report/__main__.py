"""`python -m mapex.report`: run the report command line (exit 0, or 2 on bad input)."""

import sys

from mapex.report import main

sys.exit(main())
