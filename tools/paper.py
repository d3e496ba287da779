#!/usr/bin/env python3
"""The paper's four scenarios and its 20-target comparison (Table I), for every controller.

The scenarios and the arm-angle mapping are in policy/tasks/scenarios.py; the confidence
intervals in policy/campaigns/stats.py; the runs, figures and docs block in
policy/campaigns/paper/ (its command line in `command.py`).

    tools/paper.py                  # the committed table's settings; writes runs/paper/ only
    tools/paper.py --write-docs     # ... and docs/figures/*.png + docs/results.md's block
    tools/paper.py --controllers pid --n 2 --more-seeds   # a quick look, runs/paper/ only

Without ``--write-docs`` nothing under docs/ is touched: JSON, a preview of the generated
block and the figures go to runs/paper/. ``--write-docs`` refuses a run whose settings
differ from the table it would replace (recorded in the block) unless ``--force``.
"""

from __future__ import annotations

import sys

from protocol.extras import script_needs_extra

with script_needs_extra("tools/paper.py", "sim"):
    import mujoco  # noqa: F401  (imported as the run goes: checked here, before any output)

    from policy.campaigns.paper.command import main

if __name__ == "__main__":
    sys.exit(main())
