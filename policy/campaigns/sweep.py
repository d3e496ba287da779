"""Training seed sweeps on Ray Tune: the same training run for several seeds, one trial each
(`policy.campaigns.parallel.tune_trial`), and what each trial reported. tools/sweep.py runs it.

Errors in the settings are `ValueError`; a missing Ray Tune is `CampaignError`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from policy.campaigns.parallel import import_tune, ray_session, tune_trial
from policy.rl.config import DDPGConfig
from policy.rl.overrides import apply_overrides


def sweep_config(preset: str, steps: int, overrides: list[str]) -> DDPGConfig:
    """The run every trial makes (its seed aside): a preset, a step budget, ``--set`` items."""
    if steps < 1:
        raise ValueError(f"--steps must be at least 1, got {steps}")
    try:
        base = DDPGConfig.preset(preset, total_steps=steps)
        return apply_overrides(base, overrides)
    except SystemExit as exc:  # the `--set` parser reports bad items this way
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
                "training": config.to_dict(),
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


def summarize(
    config: DDPGConfig, seeds: list[int], steps: int, trials: list[dict[str, Any]]
) -> dict[str, Any]:
    """What OUT/sweep.json keeps: the config, the trials, and the spread of their best scores."""
    summary: dict[str, Any] = {
        "config": config.to_dict(),
        "seeds": seeds,
        "steps": steps,
        "trials": trials,
    }
    scores = [t["final"]["best_score"] for t in trials if "best_score" in t["final"]]
    if scores:
        summary["best_score"] = {
            "mean": float(np.mean(scores)),
            "min": float(np.min(scores)),
            "max": float(np.max(scores)),
        }
    return summary


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
