#!/usr/bin/env python3
"""Controllers over the uncertainty envelope: its feasible corners and random draws.

One episode per arm of the envelope (policy/tasks/envelope.py): the arm's parameters, weak joint,
sensor-noise multiple and latency (`Variant.run_config`, `Variant.episode`), sensor noise on,
a start and a target drawn from the arm's own seed. Per-episode results (the arm's factors
and the metrics of docs/metrics.md) go to OUT/LABEL.json; the summary gives reached, at rest,
overshoot, settling and energy with 95 % bootstrap intervals (policy/campaigns/stats.py), the worst
arms by overshoot and the failure rate by factor level. docs/robustness.md explains it all;
policy/campaigns/robustness/ holds the logic and (`command.py`) the command line.

Seeds: arm i of a set (corners or draws) starts and aims at two points drawn uniformly in the
evaluation workspace from ``default_rng([seed, set, i])`` (set 0: corners, 1: draws), and its
sensor noise uses episode seed ``seed + 100000 * set + i``. A corner's episode therefore does
not depend on ``--max-corners``, and the first N draws of ``--draws 1000`` are ``--draws N``.

Examples:
    tools/robustness.py --controller pid ddpg-distilled --corners --draws 1000 --seed 1 --workers 1
    tools/robustness.py --controller mpc --corners --max-corners 100 --draws 200 --seed 1
    tools/robustness.py --controller ddpg-distilled --label robust \\
        --param weights=runs/x/actor.npz \\
        --corners --draws 1000 --seed 1 --write-docs
    tools/robustness.py --from runs/robustness/*.json --write-docs
"""

from __future__ import annotations

import sys

from policy.campaigns.robustness.command import main

if __name__ == "__main__":
    sys.exit(main())
