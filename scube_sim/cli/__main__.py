"""`python -m scube_sim.cli`: the `scube-sim` command."""

import sys

from . import main

sys.exit(main())
