"""Table I's runs: one controller on the random targets of one seed, as the JSON of
`Evaluation.to_dict()`, reloaded when it is the same controller, episodes and settings."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from policy.campaigns.evaluation import (
    Episode,
    Evaluation,
    RunConfig,
    evaluate,
    load_controller,
)

# ---------------------------------------------------------------- per-episode table data
#
# A table run is `Evaluation.to_dict()`: {"controller", "config", "episodes": [{"start",
# "target", "metrics": {...}, "rmse_floor", ...}], "controller_stats", ...}. The block is
# built from these dicts only, so a run reloaded with --reuse prints what a fresh one does.


def values(run: dict[str, Any], key: str) -> np.ndarray:
    """One metric (or "rmse_floor") per episode."""
    if key == "rmse_floor":
        return np.array([float(e["rmse_floor"]) for e in run["episodes"]])
    return np.array([float(e["metrics"][key]) for e in run["episodes"]])


def summary(run: dict[str, Any]) -> dict[str, float]:
    """Mean over episodes of every metric (reached as a fraction), as `Evaluation.summary`."""

    def numeric(k: str) -> bool:  # fields a newer metrics module adds may be anything
        return all(isinstance(e["metrics"].get(k), int | float | bool) for e in run["episodes"])

    keys = [k for k in run["episodes"][0]["metrics"] if numeric(k)]
    out = {k: float(np.mean(values(run, k))) for k in keys}
    out["rmse_floor"] = float(np.mean(values(run, "rmse_floor")))
    return out


def table_path(runs: Path, name: str, seed: int, main_seed: int) -> Path:
    return runs / (f"table_{name}.json" if seed == main_seed else f"table_{name}_seed{seed}.json")


def load_table(
    path: Path, name: str, config: RunConfig, episodes: Sequence[Episode]
) -> dict[str, Any] | None:
    """A saved table run, if it is this controller on exactly these episodes and settings."""
    try:
        run = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
    if run.get("controller") != name or run.get("config") != config.to_dict():
        return None
    saved = [(e["start"], e["target"]) for e in run.get("episodes", [])]
    if saved != [(ep.start.tolist(), ep.target.tolist()) for ep in episodes]:
        return None
    return run


def run_table(
    name: str,
    episodes: Sequence[Episode],
    config: RunConfig,
    path: Path,
    reuse: bool,
    console: Console,
    reused: list[str],
) -> dict[str, Any]:
    if reuse:
        run = load_table(path, name, config, episodes)
        if run is not None:
            console.print(f"  reused {path}")
            reused.append(f"{name} seed {config.seed}")
            return run
    load0 = os.getloadavg()[0]
    t0 = time.monotonic()
    # a fresh controller, so solve-time statistics cover this table only
    ev: Evaluation = evaluate(load_controller(name), episodes, config, name=name)
    run = ev.to_dict()
    run["wall_s"] = time.monotonic() - t0
    run["machine"] = {"cores": os.cpu_count(), "load1": max(load0, os.getloadavg()[0])}
    path.write_text(json.dumps(run, indent=1))
    console.print(f"  {len(episodes)} episodes in {run['wall_s']:.0f} s")
    return run
