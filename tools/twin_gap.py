#!/usr/bin/env python3
"""The gap a fitted twin closes: a controller's metrics on the hidden arm, the fitted twin and
the nominal twin, on the same episodes.

    tools/twin_gap.py --hidden HIDDEN.json --fitted arm.json        # pid and ddpg-distilled
    tools/twin_gap.py --hidden HIDDEN.json --fitted arm.json --controllers pid --episodes 8
    tools/identify.py ... --truth HIDDEN.json --check-controller pid,ddpg-distilled  # after a fit

Why: a twin is for predicting what a controller does on the arm. The issue's target is that a
controller's energy on the fitted twin is within 5 % of its energy on the arm, and its
settling time within 0.1 s; parameter errors and trajectory RMS say nothing about that
directly. The measurement is `policy.campaigns.identification.twin_gap`'s.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from policy.campaigns.evaluation import RunConfig, random_episodes
from policy.campaigns.identification.twin_gap import (
    DEFAULT_CONTROLLERS,
    finite_or_none,
    markdown,
    measure_gap,
)
from reach_sim_bridge.model.params import ArmParams, load_arm_params


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="twin_gap.py",
        description=__doc__.split("\n\n")[0] if __doc__ else "",
    )
    p.add_argument("--hidden", type=Path, required=True, metavar="PARAMS.json")
    p.add_argument("--fitted", type=Path, required=True, metavar="PARAMS.json")
    p.add_argument("--nominal", type=Path, metavar="PARAMS.json", help="default: the nominal twin")
    p.add_argument("--controllers", default=",".join(DEFAULT_CONTROLLERS))
    p.add_argument("--episodes", type=int, default=6, help="random episodes (default 6)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=RunConfig().seconds)
    p.add_argument("--json", type=Path, metavar="OUT.json", help="write the figures as JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        hidden = load_arm_params(args.hidden)
        fitted = load_arm_params(args.fitted)
        nominal = load_arm_params(args.nominal) if args.nominal else ArmParams()
        episodes = random_episodes(args.episodes, args.seed)
        config = RunConfig(seconds=args.seconds, seed=args.seed)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    names = [c.strip() for c in args.controllers.split(",") if c.strip()]
    gaps = measure_gap(names, hidden, fitted, episodes, config, nominal)
    print(markdown(gaps))
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "summary": [g.summary() for g in gaps],
                    "episodes": {g.controller: [asdict(e) for e in g.episodes] for g in gaps},
                },
                indent=1,
                default=finite_or_none,
            ),
            encoding="utf-8",
        )
    return 0 if all(g.meets_targets() for g in gaps) else 1


if __name__ == "__main__":
    sys.exit(main())
