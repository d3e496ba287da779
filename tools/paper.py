#!/usr/bin/env python3
"""The paper's four scenarios and its 20-target comparison (Table I), for every controller.

The scenarios and the arm-angle mapping are in policy/tasks/scenarios.py; the confidence
intervals in policy/campaigns/stats.py; the runs, figures and docs block in
policy/campaigns/paper/ (this script is its command line).

    tools/paper.py                  # the committed table's settings; writes runs/paper/ only
    tools/paper.py --write-docs     # ... and docs/figures/*.png + docs/results.md's block
    tools/paper.py --controllers pid --n 2 --more-seeds   # a quick look, runs/paper/ only

Without ``--write-docs`` nothing under docs/ is touched: JSON, a preview of the generated
block and the figures go to runs/paper/. ``--write-docs`` refuses a run whose settings
differ from the table it would replace (recorded in the block) unless ``--force``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from policy.campaigns.paper.command import Options, execute
from policy.campaigns.paper.settings import COMMITTED
from policy.campaigns.stats import DEFAULT_RESAMPLES

ROOT = Path(__file__).resolve().parents[1]


def build_parser() -> argparse.ArgumentParser:
    c = COMMITTED
    p = argparse.ArgumentParser(
        prog="paper.py",
        description="Run the paper's four scenarios and its random-target comparison "
        "(Table I) for each controller, with bootstrap confidence intervals. Every default "
        "is the setting of the table committed in docs/results.md. By default only "
        "runs/paper/ is written (JSON, a preview of the generated block, figures); "
        "--write-docs also writes docs/figures/*.png and the generated block of "
        "docs/results.md. Controllers that cannot be loaded (e.g. DDPG without weights) "
        "are skipped and listed.",
    )
    p.add_argument(
        "--controllers",
        nargs="+",
        default=list(c.controllers),
        help=f"entry-point names (default: {' '.join(c.controllers)})",
    )
    p.add_argument("--seed", type=int, default=c.seed, help=f"seed of Table I ({c.seed})")
    p.add_argument("--n", type=int, default=c.n, help=f"random targets per seed ({c.n})")
    p.add_argument(
        "--seconds", type=float, default=c.seconds, help=f"episode length, s ({c.seconds:g})"
    )
    p.add_argument(
        "--rate", type=float, default=c.rate_hz, help=f"control rate, Hz ({c.rate_hz:g})"
    )
    assert c.noise is not None
    p.add_argument(
        "--noise",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="sensor noise in the comparison (default: on; scenarios are always noise-free)",
    )
    p.add_argument(
        "--noise-std",
        nargs=2,
        type=float,
        default=list(c.noise),
        metavar=("RAD", "RAD_S"),
        help=f"sensor noise sigma on position and velocity ({c.noise[0]} {c.noise[1]})",
    )
    p.add_argument(
        "--perturb",
        type=float,
        default=c.perturb,
        metavar="SPREAD",
        help=f"arm parameters degraded by U(1 +- SPREAD) in the comparison ({c.perturb:g}; "
        "0 = nominal)",
    )
    p.add_argument(
        "--more-seeds",
        nargs="*",
        type=int,
        default=list(c.more_seeds),
        metavar="SEED",
        help="repeat the comparison on these seeds too and pool them in the paired "
        f"differences (default: {' '.join(map(str, c.more_seeds))}; none: --more-seeds)",
    )
    p.add_argument("--skip-table", action="store_true", help="only the four scenarios")
    p.add_argument("--skip-scenarios", action="store_true", help="only the comparison")
    p.add_argument(
        "--runs",
        type=Path,
        default=ROOT / "runs" / "paper",
        help="JSON, block preview and (without --write-docs) figures (the repository's runs/paper)",
    )
    p.add_argument(
        "--docs",
        type=Path,
        default=ROOT / "docs",
        help="docs folder: --write-docs writes DOCS/results.md's block and DOCS/figures "
        "(the repository's docs/)",
    )
    p.add_argument(
        "--write-docs",
        action="store_true",
        help="write DOCS/figures/*.png and replace the generated block of DOCS/results.md; "
        "refused when the settings differ from the table there, unless --force",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="with --write-docs: replace a table made with other settings",
    )
    p.add_argument(
        "--reuse",
        action="store_true",
        help="reload a table run from RUNS/*.json when it is the same controller on the same "
        "episodes and settings, instead of running it again (scenarios always run)",
    )
    p.add_argument(
        "--resamples",
        type=int,
        default=DEFAULT_RESAMPLES,
        help=f"bootstrap resamples ({DEFAULT_RESAMPLES})",
    )
    p.add_argument("--ci-seed", type=int, default=0, help="bootstrap seed (0)")
    return p


def main(argv: list[str] | None = None) -> int:
    return execute(Options(**vars(build_parser().parse_args(argv))))


if __name__ == "__main__":
    sys.exit(main())
