"""`python -m bmimic.sim2sim`."""

import sys

from bmimic.sim2sim.cli import main

if __name__ == "__main__":  # not when a spawned worker process imports this as __mp_main__
    sys.exit(main())
