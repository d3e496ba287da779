"""The `reach-sim` script: the simulator's command line, or one line naming the extra to install
when MuJoCo is not (`pip install reach-stack` alone brings the driver, not the simulator)."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from protocol.extras import USAGE_EXIT, MissingExtra, needs_extra


def main(argv: Sequence[str] | None = None) -> int:
    try:
        with needs_extra("reach-sim (the virtual arm)", "sim"):
            from reach_sim_bridge.cli import main as serve
    except MissingExtra as exc:
        print(f"reach-sim: error: {exc}", file=sys.stderr)
        return USAGE_EXIT
    return serve(argv)
