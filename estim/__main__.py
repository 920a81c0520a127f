"""``python -m estim``: the command line (see :mod:`estim.cli`)."""

import sys

from estim.cli import main

sys.exit(main())
