#!/usr/bin/env python3
"""Score a controller on step responses of the simulated Alpha 5 (metrics: docs/metrics.md).

Examples:
    tools/evaluate.py --controller pid --random 20 --seed 7 --out pid.json
    tools/evaluate.py --controller mpc --targets episodes.json --noise --out mpc.json

The parser and the run live in policy/campaigns/evaluate_command.py (importable, so tests and
other programs use the same command line).
"""

from __future__ import annotations

import sys

from protocol.extras import script_needs_extra

with script_needs_extra("tools/evaluate.py", "sim"):
    import mujoco  # noqa: F401  (imported as the run goes: checked here, before any output)

    from policy.campaigns.evaluate_command import main

if __name__ == "__main__":
    sys.exit(main())
