#!/usr/bin/env python3
"""Screen controllers for chatter offline: the driver's chatter guard (reach_driver/chatter.py)
replayed over direct-backend episodes, checked against an independent definition.

policy/campaigns/chatter_screen.py screens; this script is its command line.

Examples:
    tools/screen_chatter.py --controllers ddpg-distilled,ddpg-distilled-pure,pid \\
        --episodes 640,200,200 \\
        --seed 20000 --workers 2 --out screen.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from policy.campaigns.chatter_screen import LATE_ENERGY_J, LATE_WINDOW_S, Options, execute
from policy.campaigns.evaluation import add_param_option


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="screen_chatter.py",
        description=(
            "Replay the driver's chatter guard over direct-backend episodes of each "
            "controller and compare it with an independent chatter definition (energy "
            "spent over the last seconds of the episode)."
        ),
        epilog="The guard's definition and thresholds: docs/chatter.md.",
    )
    p.add_argument(
        "--controllers",
        default="ddpg-distilled,ddpg-distilled-pure,pid",
        help="comma-separated names",
    )
    p.add_argument(
        "--episodes",
        default="640,200,200",
        help="episodes per controller, one number for all or one per controller",
    )
    add_param_option(p, "--param settle=0 (every controller's): no settle supervisor")
    p.add_argument("--seed", type=int, default=20000, help="episode set and noise (as evaluate)")
    p.add_argument("--perturb", type=float, default=0.2, help="arm degradation spread (0.2)")
    p.add_argument(
        "--no-noise",
        dest="noise",
        action="store_false",
        help="the controller reads true angles (default: noisy, as evaluate.py --noise)",
    )
    p.add_argument("--seconds", type=float, default=20.0, help="episode length (20 s)")
    p.add_argument("--late-energy", type=float, default=LATE_ENERGY_J, metavar="J")
    p.add_argument("--late-window", type=float, default=LATE_WINDOW_S, metavar="S")
    p.add_argument("--workers", type=int, default=1, help="Ray workers (1: serial)")
    p.add_argument("--out", type=Path, required=True, metavar="OUT.json")
    return p


def main(argv: list[str] | None = None) -> int:
    return execute(Options(**vars(build_parser().parse_args(argv))))


if __name__ == "__main__":
    sys.exit(main())
