#!/usr/bin/env python3
"""Pick which trained actor to ship, by a rule fixed before looking at Table I's episodes.

Candidates are run directories (their `best_actor.npz`) or `.npz` files. Each one is run as
the `ddpg-distilled` controller without its settle supervisor (the actor with its reference
integral: the rule judges what was learned, which the supervisor would cover) on
- the paper's four scenarios (policy/tasks/scenarios.py: nominal arm, no noise), which it must all
reach;
- a selection set that is NOT the comparison's: ``random_episodes(--episodes, --seed)`` with
  sensor noise and +-20 % degraded parameters, the conditions of Table I. The default seed (11)
  is the set the MPC's horizon and weights were tuned on (tools/tune_mpc.py) and the
  demonstrator's energy weight was chosen on (tools/tune_expert.py), so every controller's
  choices come from the same episodes and none from seed 2020's.

- a stability screen: ``--screen`` (200) more episodes (seed ``--screen-seed``, 12), noise and
  +-20 % degraded parameters, on the training environment; an episode is
  restless when it does not come to rest (`Metrics.at_rest`, docs/metrics.md "Rest": RMS speed,
  command reversals and energy after settling). ``--workers N`` / ``--address ADDR`` run the
  screen on Ray (policy/campaigns/parallel.py) with the same results. A policy that chatters on some
  arm (seen: one joint bang-banging at the no-load speed, +-8 mrad around its target, 60 J
  instead of 4 J) is not shipped.

Rule (policy/campaigns/selection.py): among the candidates that reach every scenario and every
selection episode and have no restless episode, the one better than the reference
controller (the MPC) on the most of Table I's six metrics; ties go to the
lowest mean ratio candidate / reference over the six.
Then ship it with ``tools/train.py --run RUN --ship`` (which writes its provenance beside the
weights).

    tools/select_weights.py runs/wide-s5 runs/wide-s6 runs/perturb-s7 --out runs/select.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from policy.campaigns.evaluation import RunConfig, evaluate, load_controller, random_episodes
from policy.campaigns.parallel import CampaignError
from policy.campaigns.selection import (
    choose,
    score_candidate,
    screen,
    selection_table,
    weights_of,
)
from reach_driver.cli.tables import show_table
from reach_sim_bridge.model.sensors import SensorNoise


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="select_weights.py",
        description="Score trained actors (ddpg-distilled candidates) on the paper's scenarios "
        "and on a selection set (not Table I's episodes) against a reference controller, and "
        "name the one to ship by a fixed rule (see the module docstring).",
    )
    p.add_argument(
        "candidates",
        nargs="+",
        type=Path,
        help="run directories (their best_actor.npz) or actor .npz files",
    )
    p.add_argument("--reference", default="mpc", help="controller to beat (default mpc)")
    p.add_argument("--seed", type=int, default=11, help="selection set's seed (default 11)")
    p.add_argument("--episodes", type=int, default=20, help="selection episodes (default 20)")
    p.add_argument(
        "--perturb",
        type=float,
        default=0.2,
        metavar="SPREAD",
        help="degraded arm parameters (default 0.2, as Table I)",
    )
    p.add_argument(
        "--screen",
        type=int,
        default=200,
        help="episodes of the stability screen (default 200; 0 skips it)",
    )
    p.add_argument(
        "--screen-seed", type=int, default=12, help="stability screen's seed (default 12)"
    )
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run the stability screen on Ray with N CPUs here (pip install -e '.[scale]')",
    )
    p.add_argument("--address", metavar="ADDR", help="run the screen on the Ray cluster at ADDR")
    p.add_argument("--out", type=Path, required=True, help="JSON with every candidate's figures")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = Console()
    try:
        paths = [weights_of(c) for c in args.candidates]
        episodes = random_episodes(args.episodes, args.seed)
        config = RunConfig(noise=SensorNoise(), seed=args.seed, param_spread=args.perturb)
    except (FileNotFoundError, ValueError) as exc:
        console.print(f"[red]error:[/red] {exc}")
        return 2
    console.print(f"reference {args.reference}: {args.episodes} episodes, seed {args.seed}")
    reference = evaluate(
        load_controller(args.reference), episodes, config, name=args.reference
    ).summary()
    rows: list[dict[str, Any]] = []
    for candidate, path in zip(args.candidates, paths, strict=True):
        console.print(f"{candidate}: scenarios and {args.episodes} episodes")
        try:
            screened = (
                screen(
                    path,
                    args.screen,
                    args.screen_seed,
                    args.perturb,
                    workers=args.workers,
                    address=args.address,
                )
                if args.screen > 0
                else []
            )
        except (CampaignError, ValueError) as exc:
            console.print(f"[red]error:[/red] {escape(str(exc))}")
            return 2
        rows.append(score_candidate(candidate, path, episodes, config, reference, screened))
    best = choose(rows, reference)
    title = (
        f"selection set: seed {args.seed}, {args.episodes} episodes, noise, "
        f"perturb {args.perturb}; * = chosen"
    )
    table = selection_table(title, args.reference, reference, rows, best, args.screen)
    show_table(console, table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "args": {k: str(v) for k, v in vars(args).items()},
                "reference": reference,
                "rows": rows,
                "chosen": None if best is None else best["candidate"],
            },
            indent=1,
        )
    )
    if best is None:
        console.print("no candidate reaches every scenario and episode and comes to rest")
        return 1
    console.print(f"chosen: {best['candidate']} (ship it with tools/train.py --run ... --ship)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
