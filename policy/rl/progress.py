"""What a training run shows while it runs: timestamped log lines (train.log and the console)
and progress, as live bars on a terminal or as a log line every 30 s (`bar=False`).

The log prints through the console the bars draw on, so a line goes above the bars, never onto
them. The progress callback also ends a run at its wall-time deadline (`StopTraining`).
"""

from __future__ import annotations

import time
from pathlib import Path
from types import TracebackType

import numpy as np
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from policy.rl.trainer import Trainer, TrainState


class StopTraining(Exception):
    """Raised from the progress callback to end a run at its wall-time limit."""


class RunLog:
    """Timestamped lines to the run's train.log and to the console."""

    def __init__(self, path: Path, console: Console) -> None:
        self.console = console
        self.file = open(path, "a", buffering=1)  # noqa: SIM115

    def __call__(self, msg: str) -> None:
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        self.file.write(line + "\n")
        self.console.print(line, markup=False, highlight=False, soft_wrap=True)
        self.console.file.flush()

    def close(self) -> None:
        self.file.close()


class TrainingProgress:
    """A bar for the demonstrations (when the run collects them) and one for training up to
    `until` env steps; or, without bars, log lines. Use as a context manager around the run,
    `on_demo` as the trainer's `demo_progress` and the instance as its `progress`."""

    def __init__(
        self,
        trainer: Trainer,
        console: Console,
        log: RunLog,
        until: int,
        deadline: float | None,
        bar: bool,
    ) -> None:
        self.trainer, self.log, self.until = trainer, log, until
        self.deadline, self.bar = deadline, bar
        self.stopped_at = until
        self._last_print = 0.0
        self._t0 = time.monotonic()
        self._steps0 = trainer.state.env_steps
        config = trainer.config
        self._bars = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
            TextColumn("{task.fields[detail]}"),
            console=console,
            disable=not bar,
        )
        collects = (
            trainer.state.env_steps == 0
            and len(trainer.demos) == 0
            and config.demo_episodes > 0
            and trainer.expert is not None
        )
        self._demo_task = (
            self._bars.add_task("demonstrations", total=config.demo_episodes, detail="episodes")
            if collects
            else None
        )
        self._train_task = self._bars.add_task(
            "training", total=until, completed=trainer.state.env_steps, detail="", start=False
        )

    def __enter__(self) -> TrainingProgress:
        self._bars.__enter__()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._bars.__exit__(exc_type, exc, tb)

    def on_demo(self, done: int, total: int) -> None:
        if self._demo_task is not None:
            self._bars.update(self._demo_task, completed=done)
        if not self.bar and (done == total or done % 10 == 0):
            self.log(f"demonstrations: {done}/{total} episodes")

    def __call__(self, state: TrainState, losses: dict[str, float]) -> None:
        now = time.monotonic()
        if self.deadline is not None and now > self.deadline:
            self.stopped_at = state.env_steps
            raise StopTraining
        if now - self._last_print < (0.25 if self.bar else 30.0):
            return
        if self._last_print == 0.0:
            self._bars.start_task(self._train_task)
        self._last_print = now
        trainer = self.trainer
        explore = (  # SAC explores by its own samples: its temperature and entropy instead
            f"alpha {losses.get('alpha', np.nan):.3g} entropy {losses.get('entropy', np.nan):.2f}"
            if "alpha" in losses
            else f"eps {trainer.epsilon():.2f} bc {trainer.bc_weight():.2f}"
        )
        detail = (
            f"critic {losses.get('critic_loss', np.nan):.3g} q {losses.get('q', np.nan):.3g} "
            f"{explore}"
        )
        if self.bar:
            self._bars.update(self._train_task, completed=state.env_steps, detail=detail)
        else:
            rate = (state.env_steps - self._steps0) / max(now - self._t0, 1e-9)
            eta = (self.until - state.env_steps) / max(rate, 1e-9)
            self.log(
                f"{state.env_steps}/{self.until} {rate:.0f} steps/s eta {eta / 60:.0f} min {detail}"
            )

    def finish(self) -> None:
        """The training bar at the run's last step."""
        self._bars.update(self._train_task, completed=self.trainer.state.env_steps)
