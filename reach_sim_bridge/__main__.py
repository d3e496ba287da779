"""`python -m reach_sim_bridge`, the same as the `reach-sim` script."""

import sys

from reach_sim_bridge.launch import main

sys.exit(main())
