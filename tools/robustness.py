#!/usr/bin/env python3
"""Controllers over the uncertainty envelope: its feasible corners and random draws.

One episode per arm of the envelope (policy/tasks/envelope.py): the arm's parameters, weak joint,
sensor-noise multiple and latency (`Variant.run_config`, `Variant.episode`), sensor noise on,
a start and a target drawn from the arm's own seed. Per-episode results (the arm's factors
and the metrics of docs/metrics.md) go to OUT/LABEL.json; the summary gives reached, at rest,
overshoot, settling and energy with 95 % bootstrap intervals (policy/campaigns/stats.py), the worst
arms by overshoot and the failure rate by factor level. docs/robustness.md explains it all;
policy/campaigns/robustness/ holds the logic, this script its command line.

Seeds: arm i of a set (corners or draws) starts and aims at two points drawn uniformly in the
evaluation workspace from ``default_rng([seed, set, i])`` (set 0: corners, 1: draws), and its
sensor noise uses episode seed ``seed + 100000 * set + i``. A corner's episode therefore does
not depend on ``--max-corners``, and the first N draws of ``--draws 1000`` are ``--draws N``.

Examples:
    tools/robustness.py --controller pid ddpg --corners --draws 1000 --seed 1 --workers 1
    tools/robustness.py --controller mpc --corners --max-corners 100 --draws 200 --seed 1
    tools/robustness.py --controller ddpg --label robust --param weights=runs/x/actor.npz \\
        --corners --draws 1000 --seed 1 --write-docs
    tools/robustness.py --from runs/robustness/*.json --write-docs
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from policy.campaigns.evaluation import add_param_option
from policy.campaigns.robustness.command import Options, execute
from policy.campaigns.robustness.report import DOC


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="robustness.py",
        description="Run controllers over the uncertainty envelope (policy/tasks/envelope.py): one "
        "episode (sensor noise on, scaled per arm) on each feasible corner and/or N random "
        "arms; write per-episode results and print reached, at rest, overshoot, settling "
        "and energy with 95 % bootstrap intervals, the worst arms and failures by factor.",
        epilog="The envelope and the results: docs/robustness.md.",
    )
    p.add_argument("--controller", nargs="+", metavar="NAME", help="ddpg ddpg-pure mpc pid ...")
    p.add_argument(
        "--label",
        help="name for the results and the docs block (default: the controller's name; "
        "one controller only), e.g. robust for --param weights=FILE",
    )
    add_param_option(p, "--param weights=runs/robust/actor.npz (every controller's)")
    p.add_argument("--corners", action="store_true", help="run the envelope's feasible corners")
    p.add_argument(
        "--max-corners",
        type=int,
        metavar="K",
        help="only K corners, chosen by a permutation seeded by --seed (for slow controllers)",
    )
    p.add_argument("--draws", type=int, metavar="N", help="run N feasible random arms")
    p.add_argument(
        "--params",
        metavar="FILE.json",
        help="the arm the envelope spreads around: ArmParams fields, the rest nominal (as in "
        'tools/evaluate.py), e.g. {"friction_holds": true} for friction that holds',
    )
    p.add_argument(
        "--twin",
        action="store_true",
        help="give the controller each arm's twin, its parameters and loop latency, as an "
        "identification (tools/identify.py) would: for controllers that take params= and "
        "latency_periods= (lambda)",
    )
    p.add_argument(
        "--twin-error",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="with --twin: scale each twin's friction, damping, armature, masses and volumes "
        "by independent factors in 1 +- FRACTION, seeded per arm (default 0: exact)",
    )
    p.add_argument(
        "--twin-from",
        type=Path,
        metavar="DIR",
        help="with --twin: each arm's twin from DIR/SET-INDEX.json (an identification's fit, "
        "tools/identify.py), only the arms that have one; --twin-error is then only how far "
        "the controller is told to trust it",
    )
    p.add_argument(
        "--export-arms",
        type=Path,
        metavar="DIR",
        help="do not run: write each planned arm as DIR/SET-INDEX.json, a reach-sim --params "
        "file (its sensor noise and latency under _envelope), to identify it",
    )
    p.add_argument(
        "--identify",
        type=Path,
        metavar="DIR",
        help="do not run controllers: identify each planned arm through the driver (reach-sim "
        "serving it on a pty, tools/identify.py exciting and fitting it; about 12 min of one "
        "CPU each) into DIR/SET-INDEX.json, the fits --twin-from DIR reads; --workers and "
        "--address run arms in parallel; arms already in DIR are skipped",
    )
    p.add_argument(
        "--identify-args",
        default="--max-current 600 --watchdog 1.0",
        metavar="ARGS",
        help="with --identify: options for tools/identify.py (default: '--max-current 600 "
        "--watchdog 1.0', the envelope's weak drives need the current, a loaded host the "
        "watchdog's slack)",
    )
    p.add_argument(
        "--sim-speed",
        type=float,
        default=1.0,
        metavar="X",
        help="with --identify: reach-sim --speed (default 1: host stalls stay out of the data)",
    )
    p.add_argument("--seed", type=int, default=1, help="seed of the draws and episodes (1)")
    p.add_argument("--seconds", type=float, default=20.0, help="episode length (20 s)")
    p.add_argument("--rate", type=float, default=20.0, metavar="HZ", help="control rate (20)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("runs/robustness"),
        metavar="DIR",
        help="where LABEL.json goes (default runs/robustness)",
    )
    p.add_argument(
        "--workers", type=int, metavar="N", help="run on Ray with N CPUs on this machine"
    )
    p.add_argument("--address", metavar="ADDR", help="run on the Ray cluster at ADDR")
    p.add_argument(
        "--from",
        dest="from_files",
        nargs="+",
        type=Path,
        metavar="FILE.json",
        help="do not run: report (and with --write-docs, write) saved results",
    )
    p.add_argument(
        "--write-docs",
        action="store_true",
        help="regenerate each label's block in docs/robustness.md",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="with --write-docs: replace a block made with other settings",
    )
    p.add_argument(
        "--overshoot-by",
        nargs="+",
        metavar="FACTOR",
        help="also print the overshoot grouped by these factors' levels (low / high half of "
        "each range; the weak joint by letter), e.g. latency_periods coulomb_edc",
    )
    p.add_argument("--doc", type=Path, default=DOC, help=argparse.SUPPRESS)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return execute(Options(**vars(args)), command="tools/robustness.py " + " ".join(argv))


if __name__ == "__main__":
    sys.exit(main())
