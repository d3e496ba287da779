"""One sitting of a training run in its directory: build (or resume) the trainer, train to a
step count or a wall-time limit with progress shown, and always leave a checkpoint, also on
Ctrl-C or SIGTERM (then the shell's exit status, 128 + the signal). tools/train.py's run.
"""

from __future__ import annotations

import json
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console

from policy.rl.overrides import apply_on_resume
from policy.rl.progress import RunLog, StopTraining, TrainingProgress
from policy.rl.run_dir import RunStart
from policy.rl.trainer import Trainer, make_expert


@dataclass
class Sitting:
    """How long this sitting trains and what it shows: `until` env steps in total (None: the
    config's total_steps), at most `hours` of wall time, a checkpoint every
    `checkpoint_minutes`, bars (`bar`) or log lines."""

    until: int | None = None
    hours: float | None = None
    checkpoint_minutes: float = 10.0
    bar: bool = True


def train_run(
    run_dir: Path,
    start: RunStart,
    resume: bool,
    arm_factory: Any,
    sitting: Sitting,
    command: str = "",
) -> int:
    """Train the run in `run_dir` (new, or resumed from its checkpoint) for one sitting; the
    exit status: 0, or 128 + the signal that interrupted it. `command` (how the run was
    started and resumed) goes into each exported actor's provenance."""
    config = start.config
    console = Console(highlight=False)
    log = RunLog(run_dir / "train.log", console)
    trainer = Trainer(
        config,
        run_dir,
        expert=make_expert(config),
        arm_factory=arm_factory,
        log=log,
        command=command,
    )
    if resume:
        trainer.load()
        apply_on_resume(trainer, start.target)
        config = trainer.config
        config.total_steps = max(config.total_steps, trainer.state.env_steps)
        log(f"resumed at {trainer.state.env_steps} env steps")
        for change in start.changes:
            log(f"--set on resume: {change}")
    else:
        log(f"new run {run_dir} config={config.name} seed={config.seed}")
    (run_dir / "config.json").write_text(json.dumps(config.to_dict(), indent=1))

    until = config.total_steps if sitting.until is None else sitting.until
    if until <= trainer.state.env_steps:
        raise SystemExit(f"--until {until}: the run is already at {trainer.state.env_steps} steps")
    deadline = time.monotonic() + sitting.hours * 3600 if sitting.hours else None
    progress = TrainingProgress(trainer, console, log, until, deadline, sitting.bar)
    trainer.demo_progress = progress.on_demo

    interrupted: list[int] = []

    def on_signal(signum: int, frame: object) -> None:
        interrupted.append(signum)
        raise KeyboardInterrupt  # checkpoint below

    # SIGTERM checkpoints like Ctrl-C; a job started with `&` from a script ignores SIGINT, so
    # take it back too
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        with progress:
            trainer.run(
                until_steps=until,
                checkpoint_every_s=60 * sitting.checkpoint_minutes,
                progress=progress,
                csv_path=run_dir / "train.csv",
            )
            progress.finish()
    except StopTraining:
        log(f"time limit reached at {progress.stopped_at} env steps")
    except KeyboardInterrupt:
        name = signal.Signals(interrupted[0]).name if interrupted else "SIGINT"
        log(f"interrupted ({name}): saving a checkpoint")
    finally:
        trainer.close()
    history = trainer.state.history
    if not history or history[-1]["env_steps"] != trainer.state.env_steps:
        trainer.evaluate_and_keep_best()
    trainer.save()
    log(
        f"checkpoint saved at {trainer.state.env_steps} env steps "
        f"({trainer.state.wall_s / 3600:.2f} h of training); best score "
        f"{trainer.state.best_score:.3f} -> {run_dir / 'best_actor.npz'}"
    )
    log.close()
    if interrupted:  # the shell's convention: 128 + the signal (130 for Ctrl-C, 143 for TERM)
        return 128 + interrupted[0]
    return 0
