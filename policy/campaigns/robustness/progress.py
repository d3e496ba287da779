"""A campaign's progress: a bar on a terminal, a line with an ETA every 50 episodes in a log."""

from __future__ import annotations

import time

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from policy.tasks.episodes import EpisodeResult


class ProgressLog:
    """A progress bar on a terminal; a line every 50 episodes (with an ETA) in a log file."""

    def __init__(self, label: str, total: int, console: Console, quiet: bool) -> None:
        self.label, self.total, self.console, self.quiet = label, total, console, quiet
        self.bar = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("{task.fields[last]}"),
            console=console,
            disable=quiet or not console.is_terminal,
        )
        self.task = self.bar.add_task(label, total=total, last="")
        self.count = 0
        self.t0 = time.monotonic()

    def __enter__(self) -> ProgressLog:
        self.bar.__enter__()
        self.t0 = time.monotonic()
        return self

    def __exit__(self, *exc: object) -> None:
        self.bar.__exit__(None, None, None)

    def done(self, i: int, r: EpisodeResult) -> None:
        self.count += 1
        mark = "reached" if r.metrics.reached else "NOT reached"
        self.bar.update(self.task, advance=1, last=f"#{i} {mark}")
        if not self.console.is_terminal and not self.quiet and self.count % 50 == 0:
            el = time.monotonic() - self.t0
            eta = el / self.count * (self.total - self.count)
            self.console.print(
                f"{self.label}: {self.count}/{self.total} in {el:.0f} s (eta {eta:.0f} s)"
            )
