#!/usr/bin/env python3
"""Score a controller on step responses of the simulated Alpha 5 (metrics: docs/metrics.md).

Examples:
    tools/evaluate.py --controller pid --random 20 --seed 7 --out pid.json
    tools/evaluate.py --controller mpc --targets episodes.json --noise --out mpc.json

policy/campaigns/evaluate_command.py runs it; this script is its command line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from policy.campaigns.evaluate_command import Options, execute
from policy.campaigns.evaluation import DEFAULT_RATE_HZ, DEFAULT_SECONDS, add_param_option


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="evaluate.py",
        description=(
            "Run a controller closed-loop on the MuJoCo Alpha 5 for a set of step episodes "
            "(start -> target, arm angles in rad, joint order E D C B) and write per-episode "
            "metrics and their means to JSON. The controller sees q and qdot (noisy with "
            "--noise) once per control period; its currents (mA) are held for the period."
        ),
        epilog="Metrics are defined in docs/metrics.md; results in docs/results.md.",
    )
    p.add_argument(
        "--controller",
        required=True,
        help="controller entry-point name in reach_stack.controllers (ddpg, mpc, pid)",
    )
    add_param_option(p, "--param horizon=15")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--targets",
        type=Path,
        metavar="FILE",
        help='JSON list of {"start": [E,D,C,B], "target": [E,D,C,B], '
        '"torque_scale": [4 numbers, optional]}',
    )
    src.add_argument(
        "--random",
        type=int,
        metavar="N",
        help="draw N starts and targets uniformly in the evaluation workspace "
        "E [0.4, 5.8], D [0.5, 2.9], C [0.5, 2.9], B [0.5, 2.8]",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed for --random episodes and for the sensor noise (default 0)",
    )
    p.add_argument(
        "--noise",
        action="store_true",
        help="add sensor noise to what the controller sees "
        "(sigma 0.002 rad on q, 0.02 rad/s on qdot)",
    )
    p.add_argument(
        "--perturb",
        type=float,
        default=0.0,
        metavar="SPREAD",
        help="randomly degrade each episode's arm: friction, armature, link masses "
        "and buoyancy each scaled by U(1-SPREAD, 1+SPREAD), e.g. 0.2 "
        "(default 0: the nominal arm)",
    )
    p.add_argument(
        "--params",
        type=Path,
        metavar="FILE.json",
        help="run every episode on the arm this parameter file describes (ArmParams "
        "field names, any subset, E D C B; as tools/identify.py writes); --perturb then "
        "spreads around it (default: the nominal arm)",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=DEFAULT_SECONDS,
        help=f"episode length in seconds (default {DEFAULT_SECONDS:g})",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=DEFAULT_RATE_HZ,
        metavar="HZ",
        help=f"control rate (default {DEFAULT_RATE_HZ:g} Hz, the env's default)",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="OUT.json",
        help="where to write the per-episode results and the summary",
    )
    p.add_argument(
        "--via-driver",
        action="store_true",
        help="run through the serial protocol (reach_driver -> virtual arm on a pty) "
        "instead of stepping the simulator directly; metrics still use the "
        "simulator's true angles (policy/campaigns/via_driver.py)",
    )
    p.add_argument(
        "--sim-speed",
        type=float,
        default=4.0,
        metavar="X",
        help="with --via-driver: simulator speed-up (default 4)",
    )
    p.add_argument(
        "--baud",
        type=int,
        metavar="BAUD",
        help="with --via-driver: throttle the pty like a serial line, e.g. 115200",
    )
    p.add_argument(
        "--record",
        type=Path,
        metavar="FILE.rrd",
        help="also write a Rerun recording of every episode",
    )
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run episodes in parallel on Ray with N CPUs on this machine (results are the "
        "serial run's: each episode's randomness depends on its seed only); needs the "
        "optional extra: pip install -e '.[scale]'",
    )
    p.add_argument(
        "--address",
        metavar="ADDR",
        help="run episodes on the Ray cluster at ADDR (e.g. ray://head:10001 or auto); "
        "its nodes need reach-stack installed",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar or table")
    return p


def main(argv: list[str] | None = None) -> int:
    return execute(Options(**vars(build_parser().parse_args(argv))))


if __name__ == "__main__":
    sys.exit(main())
