#!/usr/bin/env python3
"""Training seed sweeps on Ray Tune: the same training run for several seeds, one trial each.

Each trial is `policy.campaigns.parallel.tune_trial`: the trainer's Python API
(`policy.rl.trainer.Trainer`, as tools/train.py drives it) for ``--steps`` env steps in OUT/seed-N,
reporting every checkpoint evaluation to Tune (`ray.tune.report`): the trainer's selection score,
the nominal set's reached fraction, overshoot and energy. Locally by default (``ray.init`` with
``--workers`` CPUs, one trial per CPU), on a cluster with ``--address``. The summary prints
each seed's final and best score and their spread; OUT/sweep.json keeps them.

Examples:
    tools/sweep.py --seeds 0 1 2 --steps 200000 --out runs/sweep-scratch
    tools/sweep.py --ablate no-away --seeds 0 1 2 --steps 200000 --out runs/ablation/no-away
    tools/sweep.py --seeds 0 1 --steps 400 --set eval_every=200 --set demo_episodes=0 \\
        --out runs/sweep-tiny
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from protocol.extras import script_needs_extra

with script_needs_extra("tools/sweep.py", "train"):
    from policy.campaigns.ablation import ingredient
    from policy.campaigns.parallel import CampaignError
    from policy.campaigns.sweep import run_sweep, summarize, sweep_config


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="sweep.py",
        description="Train the same configuration for several seeds on Ray Tune (one trial "
        "per seed, each reporting its checkpoint evaluations) and summarise the spread.",
        epilog="docs/training.md, 'Seed sweeps'. Needs Ray Tune: pip install 'ray[tune]'.",
    )
    p.add_argument(
        "--config",
        default="scratch",
        choices=["scratch", "paper", "paper-per-joint", "ours", "robust"],
        help="preset, a classmethod of policy.rl.config.DDPGConfig (scratch)",
    )
    p.add_argument("--seeds", type=int, nargs="+", required=True, metavar="SEED")
    p.add_argument("--steps", type=int, required=True, help="env steps per trial")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field as tools/train.py --set does (repeatable)",
    )
    p.add_argument(
        "--ablate",
        metavar="INGREDIENT",
        help="switch one ingredient of the recipe off (its overrides come before --set); "
        "tools/ablation.py --list names them",
    )
    p.add_argument("--out", type=Path, required=True, help="sweep directory (runs, Tune's logs)")
    p.add_argument("--workers", type=int, metavar="N", help="CPUs on this machine (all)")
    p.add_argument("--address", metavar="ADDR", help="run the trials on the Ray cluster at ADDR")
    p.add_argument("--quiet", action="store_true", help="no Tune status table")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = Console(stderr=True, soft_wrap=True)
    try:
        overrides = list(args.set)
        if args.ablate is not None:
            overrides = [*ingredient(args.ablate).overrides, *overrides]
        config = sweep_config(args.config, args.steps, overrides)
        trials = run_sweep(
            config, args.seeds, args.out, args.workers, args.address, 0 if args.quiet else 1
        )
    except (ValueError, CampaignError) as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}")
        return 2
    summary = summarize(config, args.seeds, args.steps, trials)
    (args.out / "sweep.json").write_text(json.dumps(summary, indent=1), encoding="utf-8")
    out = Console()
    for t in trials:
        f = t["final"]
        if t["error"]:
            out.print(f"seed {t['seed']}: [red]failed[/red] {escape(t['error'])}")
        else:
            out.print(
                f"seed {t['seed']}: {f.get('env_steps')} steps, "
                f"score {f.get('score', float('nan')):.3f} "
                f"(best {f.get('best_score', float('nan')):.3f}), reached {f.get('reached')}, "
                f"{f.get('training_iteration')} reports -> {escape(str(f.get('run_dir')))}"
            )
    if "best_score" in summary:
        s = summary["best_score"]
        out.print(f"best score over seeds: mean {s['mean']:.3f}, {s['min']:.3f} .. {s['max']:.3f}")
    console.print(f"wrote {args.out / 'sweep.json'}")
    return 1 if any(t["error"] for t in trials) else 0


if __name__ == "__main__":
    sys.exit(main())
