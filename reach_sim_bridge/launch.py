"""The `reach-sim` script: the simulator's command line, or one line naming the extra to install
when MuJoCo is not (`pip install reach-stack` alone brings the driver, not the simulator)."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from protocol.extras import MissingExtra, needs_extra

USAGE_EXIT = 2  # as for a bad command line: nothing was started


def main(argv: Sequence[str] | None = None) -> int:
    try:
        with needs_extra("reach-sim (the virtual arm)", "sim"):
            from reach_sim_bridge.cli import main as serve
    except MissingExtra as exc:
        print(f"reach-sim: error: {exc}", file=sys.stderr)
        return USAGE_EXIT
    return serve(argv)
