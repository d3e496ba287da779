#!/usr/bin/env python3
"""Training seed sweeps on Ray Tune: the same training run for several seeds, one trial each.

Each trial is `policy.campaigns.parallel.tune_trial`: the trainer's Python API
(`policy.rl.trainer.Trainer`, as tools/train.py drives it) for ``--steps`` env steps in OUT/seed-N,
reporting every checkpoint evaluation to Tune (`ray.tune.report`): the trainer's selection score,
the nominal set's reached fraction, overshoot and energy. Locally by default (``ray.init`` with
``--workers`` CPUs, one trial per CPU), on a cluster with ``--address``. The summary prints
each seed's final and best score and their spread; OUT/sweep.json keeps them.

Examples:
    tools/sweep.py --config ours --seeds 0 1 2 --steps 200000 --out runs/sweep-ours
    tools/sweep.py --seeds 0 1 --steps 400 --set eval_every=200 --set demo_episodes=0 \\
        --out runs/sweep-tiny
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape

from policy.campaigns.parallel import CampaignError, import_tune, ray_session, tune_trial
from policy.rl.config import DDPGConfig

ROOT = Path(__file__).resolve().parents[1]


def _train_tool() -> ModuleType:
    """tools/train.py, for its `--set` parser (one parser for both tools)."""
    spec = importlib.util.spec_from_file_location("train_tool", ROOT / "tools" / "train.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def sweep_config(preset: str, steps: int, overrides: list[str]) -> DDPGConfig:
    """The run every trial makes (its seed aside): a preset, a step budget, ``--set`` items."""
    if steps < 1:
        raise ValueError(f"--steps must be at least 1, got {steps}")
    try:
        base = DDPGConfig.preset(preset, total_steps=steps)
        return _train_tool().apply_overrides(base, overrides)  # type: ignore[no-any-return]
    except SystemExit as exc:  # train.py's parser reports bad --set items this way
        raise ValueError(str(exc)) from exc


def run_sweep(
    config: DDPGConfig,
    seeds: list[int],
    out: Path,
    workers: int | None = None,
    address: str | None = None,
    verbose: int = 1,
) -> list[dict[str, Any]]:
    """A `ray.tune.Tuner` over the seed grid; per trial its reports (in order) and status."""
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds must be distinct, got {seeds}")
    tune = import_tune()
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    with ray_session(workers, address):
        tuner = tune.Tuner(
            tune.with_resources(tune_trial, {"cpu": 1}),
            param_space={
                "seed": tune.grid_search(seeds),
                "ddpg": config.to_dict(),
                "root": str(out),
            },
            tune_config=tune.TuneConfig(metric="score", mode="max"),
            run_config=tune.RunConfig(name="tune", storage_path=str(out), verbose=verbose),
        )
        grid = tuner.fit()
        trials = []
        for i in range(len(grid)):
            result = grid[i]
            trials.append(
                {
                    "seed": result.config["seed"],
                    "error": None if result.error is None else str(result.error),
                    "final": _clean(result.metrics or {}),
                    "reports": _reports(Path(result.path)),
                    "path": result.path,
                }
            )
    trials.sort(key=lambda t: t["seed"])
    return trials


_KEYS = (
    "seed",
    "env_steps",
    "score",
    "best_score",
    "reached",
    "overshoot_pct",
    "energy_j",
    "run_dir",
    "training_iteration",
)


def _reports(trial_dir: Path) -> list[dict[str, Any]]:
    """Every report of a trial, from Tune's own record of them (result.json, one per line)."""
    path = trial_dir / "result.json"
    if not path.exists():
        return []
    lines = path.read_text(encoding="utf-8").splitlines()
    return [_clean(json.loads(line)) for line in lines if line.strip()]


def _clean(metrics: dict[str, Any]) -> dict[str, Any]:
    return {k: metrics[k] for k in _KEYS if k in metrics}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="sweep.py",
        description="Train the same configuration for several seeds on Ray Tune (one trial "
        "per seed, each reporting its checkpoint evaluations) and summarise the spread.",
        epilog="docs/robustness.md, 'Seed sweeps'. Needs Ray Tune: pip install 'ray[tune]'.",
    )
    p.add_argument("--config", default="ours", choices=["ours", "paper"], help="preset (ours)")
    p.add_argument("--seeds", type=int, nargs="+", required=True, metavar="SEED")
    p.add_argument("--steps", type=int, required=True, help="env steps per trial")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config field as tools/train.py --set does (repeatable)",
    )
    p.add_argument("--out", type=Path, required=True, help="sweep directory (runs, Tune's logs)")
    p.add_argument("--workers", type=int, metavar="N", help="CPUs on this machine (all)")
    p.add_argument("--address", metavar="ADDR", help="run the trials on the Ray cluster at ADDR")
    p.add_argument("--quiet", action="store_true", help="no Tune status table")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = Console(stderr=True)
    try:
        config = sweep_config(args.config, args.steps, args.set)
        trials = run_sweep(
            config, args.seeds, args.out, args.workers, args.address, 0 if args.quiet else 1
        )
    except (ValueError, CampaignError) as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}")
        return 2
    summary = {
        "config": config.to_dict(),
        "seeds": args.seeds,
        "steps": args.steps,
        "trials": trials,
    }
    scores = [t["final"]["best_score"] for t in trials if "best_score" in t["final"]]
    if scores:
        summary["best_score"] = {
            "mean": float(np.mean(scores)),
            "min": float(np.min(scores)),
            "max": float(np.max(scores)),
        }
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
    if scores:
        s = summary["best_score"]
        out.print(f"best score over seeds: mean {s['mean']:.3f}, {s['min']:.3f} .. {s['max']:.3f}")
    console.print(f"wrote {args.out / 'sweep.json'}")
    return 1 if any(t["error"] for t in trials) else 0


if __name__ == "__main__":
    sys.exit(main())
