"""A training run's directory: the config a new or resumed run starts from, the record of every
command given (commands.txt), and shipping its best actor with how it was made.

A run directory holds config.json, train.csv, eval.jsonl, best_actor.npz/.json, checkpoint.pt
(+ buffers), commands.txt and train.log. Errors are `SystemExit` naming the flag, as the command
line reports them.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from policy.controllers.weights import LEARNED_WEIGHTS, TrainingStage
from policy.rl.checkpoint import provenance
from policy.rl.config import DDPGConfig
from policy.rl.overrides import apply_overrides, resume_overrides
from protocol.models import ALPHA5, ArmModel

CHECKPOINT = "checkpoint.pt"
COMMANDS = "commands.txt"


@dataclass
class RunStart:
    """What a run starts from: `config` builds the trainer (on resume, the checkpoint's own),
    `target` is what it continues with (`--set` and `--steps` applied), `changes` says what a
    resume's `--set` changed ("field old -> new")."""

    config: DDPGConfig
    target: DDPGConfig
    changes: list[str] = field(default_factory=list)


def start_run(
    run_dir: Path,
    resume: bool,
    preset: str,
    seed: int,
    steps: int | None,
    overrides: list[str],
    arm: ArmModel | None = None,
) -> RunStart:
    """The config of a new run (preset on `arm`, the Alpha 5 if None; seed, steps, `--set`),
    refused if `run_dir` already holds one; or of the run in `run_dir` resumed (`--set`
    limited to what a resume can take; `arm`, if given, must be the run's)."""
    if resume:
        if not (run_dir / CHECKPOINT).exists():
            raise SystemExit(f"--resume: no checkpoint in {run_dir}")
        # The checkpoint's own config: what its networks and buffer were made with (config.json
        # may be newer, from a resume killed before it saved).
        saved = torch.load(run_dir / CHECKPOINT, weights_only=False)["config"]
        config = DDPGConfig.from_dict(saved)
        if arm is not None and arm.name != config.env.arm.value:
            raise SystemExit(
                f"--arm {arm.name}: the run in {run_dir} trains the {config.env.model.title}"
            )
        target = config
        changes: list[str] = []
        if overrides:
            target, changes = resume_overrides(config, overrides)
        if steps is not None:
            target.total_steps = steps
        return RunStart(config, target, changes)
    if (run_dir / CHECKPOINT).exists():
        raise SystemExit(f"{run_dir} already holds a run; use --resume or another --run")
    fields: dict[str, Any] = {"seed": seed}
    if steps is not None:
        fields["total_steps"] = steps
    config = DDPGConfig.preset(preset, **fields)
    if arm is not None:
        try:
            config = config.on(arm)
        except ValueError as exc:
            raise SystemExit(f"--arm {arm.name}: {exc}") from None
    config = apply_overrides(config, overrides)
    return RunStart(config, config)


def record_command(run_dir: Path, argv: list[str]) -> None:
    """Append the command (tools/train.py and its arguments) to the run's commands.txt."""
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / COMMANDS, "a") as fh:
        fh.write(" ".join([".venv/bin/python", "tools/train.py", *argv]) + "\n")


def ship(run_dir: Path, dest: Path = LEARNED_WEIGHTS) -> Path:
    """Copy the run's best evaluated actor, with how it was made, to the shipped weights."""
    src = run_dir / "best_actor.npz"
    if not src.exists():
        raise SystemExit(f"--ship: {src} does not exist (no evaluation yet?)")
    meta = json.loads(src.with_suffix(".json").read_text())
    arm = meta.get("arm", ALPHA5.name)
    if arm != ALPHA5.name and dest.resolve() == LEARNED_WEIGHTS.resolve():
        raise SystemExit(
            f"--ship: {run_dir} trained an actor for {arm}; the shipped `ddpg` weights are the "
            "Alpha 5's: give --ship-as FILE.npz"
        )
    commands = (
        (run_dir / COMMANDS).read_text().splitlines() if (run_dir / COMMANDS).exists() else []
    )
    meta.update(
        {
            "command": commands[0] if commands else None,
            "commands": commands,
            "seed": meta["config"]["seed"],
            "training_time_s": round(float(meta.get("wall_s", float("nan"))), 1),
            "training_env_steps": meta.get("env_steps"),
            "run": run_dir.name,
            "shipped_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    )
    if "provenance" not in meta:  # an actor saved before provenance was recorded
        stage = TrainingStage(
            run=run_dir.name,
            env_steps=int(meta["env_steps"]),
            wall_s=float(meta["wall_s"]) if "wall_s" in meta else None,
            seed=int(meta["config"]["seed"]),
            command=" && ".join(commands),
        )
        config = DDPGConfig.from_dict(meta["config"])
        meta["provenance"] = provenance(config, stage).to_dict()
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dest)
    dest.with_suffix(".json").write_text(json.dumps(meta, indent=1))
    return dest
