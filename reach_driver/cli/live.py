"""What the arm is doing while `run` and `move` go on, on stderr (stdout keeps the results).

On a terminal, a rich `Live` table refreshed a few times a second from its own thread (the
control loop's hook only stores the latest step); otherwise (piped, CI) one plain line a
second, plus one at the first step and one at the end.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from types import TracebackType

import numpy as np
from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from protocol.alpha5 import JOINT_LETTERS
from reach_driver.cli.render import measured
from reach_driver.cli.tables import fitted
from reach_driver.records import StepHook, StepRecord

log = logging.getLogger("reach_driver.cli.live")

REFRESH_HZ = 4
LINE_EVERY_S = 1.0


def chain(*hooks: StepHook | None) -> StepHook | None:
    """One hook calling each given one in turn (the recorder and the live view)."""
    present = [h for h in hooks if h is not None]
    if not present:
        return None
    if len(present) == 1:
        return present[0]

    def each(record: StepRecord) -> None:
        for hook in present:
            hook(record)

    return each


def _signed(values: Sequence[float] | np.ndarray | None, digits: int) -> list[str]:
    if values is None:
        return ["-"] * 4
    return ["-" if not math.isfinite(v) else f"{v:+.{digits}f}" for v in values]


class RunView:
    """The live view of a `run`: `on_step` for the loop, a context manager around it."""

    def __init__(self, console: Console, seconds: float, *, enabled: bool = True) -> None:
        self.console = console
        self.seconds = seconds
        self.enabled = enabled
        self.live_mode = enabled and console.is_terminal
        self._latest: StepRecord | None = None
        self._walls: deque[float] = deque(maxlen=200)
        self._lock = threading.Lock()
        self._live: Live | None = None
        self._next_line = -math.inf
        self._lines = 0
        self._broken = False

    # -- the hook (the control loop's thread: keep it cheap, never raise) ------------------
    def on_step(self, record: StepRecord) -> None:
        if not self.enabled or self._broken:
            return
        try:
            with self._lock:
                self._latest = record
                self._walls.append(record.wall_t)
            if not self.live_mode:
                now = time.monotonic()
                if now >= self._next_line:
                    self._next_line = now + LINE_EVERY_S
                    self._print_line(record)
        except Exception:  # a broken view must not stop the arm's control
            log.exception("live view failed; continuing without it")
            self._broken = True

    def rate_hz(self) -> float:
        """Steps per wall second over the last second or so."""
        with self._lock:
            walls = list(self._walls)
        if len(walls) < 2:
            return math.nan
        recent = [w for w in walls if w >= walls[-1] - 1.0]
        if len(recent) < 2:
            recent = walls[-2:]
        span = recent[-1] - recent[0]
        return (len(recent) - 1) / span if span > 0 else math.nan

    # -- plain lines ------------------------------------------------------------------------
    def line(self, r: StepRecord) -> str:
        err = r.target - r.q
        current = r.current_mA if r.current_mA is not None else r.command_mA
        source = "I" if r.current_mA is not None else "cmd"
        parts = [
            f"t {r.t:5.1f}/{self.seconds:g} s",
            "error [rad] "
            + " ".join(f"{j} {e}" for j, e in zip(JOINT_LETTERS, _signed(err, 3), strict=True)),
            f"max |e| {float(np.nanmax(np.abs(err))):.3f}",
            f"{source} [mA] " + " ".join(measured(v, ".0f") for v in current),
            f"loop {measured(self.rate_hz(), '.1f')} Hz",  # one step is no rate yet
            f"frames {r.good_frames} ok {r.bad_frames} bad",
            f"state age {r.state_age_s * 1e3:.1f} ms",
        ]
        return " | ".join(parts)

    def _print_line(self, r: StepRecord) -> None:
        self._lines += 1
        self.console.print(self.line(r), soft_wrap=True, highlight=False, markup=False)

    # -- the live table ---------------------------------------------------------------------
    def render(self) -> Table | Text:
        with self._lock:
            r = self._latest
        if r is None:
            return Text("run: waiting for the arm's first state ...")
        err = r.target - r.q
        table = Table(title=f"run: t {r.t:.1f} of {self.seconds:g} s, step {r.step}")
        for column in (
            "joint",
            "angle [rad]",
            "target [rad]",
            "error [rad]",
            "current [mA]",
            "command [mA]",
        ):
            table.add_column(escape(column), justify="right")
        currents = _signed(r.current_mA, 0)
        for row in zip(
            JOINT_LETTERS,
            [f"{v:.4f}" for v in r.q],
            [f"{v:.4f}" for v in r.target],
            _signed(err, 4),
            currents,
            _signed(r.command_mA, 0),
            strict=True,
        ):
            table.add_row(*row)
        health = "[green]good[/]" if r.bad_frames == 0 else f"[yellow]{r.bad_frames} bad[/]"
        table.caption = (
            f"loop {measured(self.rate_hz(), '.1f')} Hz | frames {r.good_frames} ok, {health} "
            f"| state age {r.state_age_s * 1e3:.1f} ms | latency {r.latency_s * 1e3:.1f} ms"
            + (" | [yellow]saturated[/]" if r.saturated else "")
            + (" | [yellow]barrier[/]" if r.barrier else "")
        )
        return table

    def _shown(self) -> RenderableType:
        shown = self.render()
        return fitted(self.console, shown) if isinstance(shown, Table) else shown

    # -- around the run ---------------------------------------------------------------------
    def __enter__(self) -> RunView:
        if self.live_mode:
            self._live = Live(
                get_renderable=lambda: Group(self._shown()),
                console=self.console,
                refresh_per_second=REFRESH_HZ,
                transient=True,  # the summary that follows says it all
                redirect_stdout=False,
            )
            self._live.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None
        elif self.enabled and not self._broken:
            with self._lock:
                last = self._latest
            if last is not None and self._next_line > -math.inf:
                self._print_line(last)  # where it ended


class MoveView:
    """`move`'s progress: a line a second of the remaining error (off a terminal), or
    nothing (on one the caller shows a progress bar)."""

    def __init__(self, console: Console, *, enabled: bool = True) -> None:
        self.console = console
        self.enabled = enabled and not console.is_terminal
        self._next = -math.inf
        self._started = time.monotonic()

    def update(self, err: np.ndarray, jaw_err: float | None, force: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (now < self._next and not force):
            return
        self._next = now + LINE_EVERY_S
        text = " ".join(f"{j} {e}" for j, e in zip(JOINT_LETTERS, _signed(err, 3), strict=True))
        jaw = f" jaw {jaw_err:+.2f} mm" if jaw_err is not None else ""
        self.console.print(
            f"move {now - self._started:5.1f} s | error [rad] {text}{jaw} | max |e| "
            f"{float(np.max(np.abs(err))):.3f}",
            soft_wrap=True,
            highlight=False,
            markup=False,
        )
