"""Where a control loop's time goes: each gap between two commands, taken apart.

The watchdog judges the gap between two commands, so that is what is measured: its
percentiles over the run (`GapStats`), and for the longest gaps what filled them (`Gap`):
the wait for the arm's next state (split into the arm or the reader being late, and the loop
thread being slow to wake once the state was complete), the controller, the step hook
(recorder, viewer, live view), garbage collection in any thread of the process, and the loop
thread's own CPU time and, where Linux reports it (/proc/thread-self/schedstat), the time it
was runnable but given no CPU. What is left is time the loop thread was neither running nor
waiting for a CPU outside those parts: it waited for the GIL or for I/O.

One `GapLog` per run, used from the loop's thread only (`GcPauses` is fed by the collector,
which runs with the GIL held, so its sums never race).
"""

from __future__ import annotations

import gc
import heapq
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import numpy as np

from reach_driver.watchdog import LoopTiming

#: How many of the longest gaps a run keeps, taken apart.
KEPT_GAPS = 5


class GcPauses:
    """Garbage-collection pauses while registered (`gc.callbacks`, as a context manager):
    their total, count, longest and, per generation, the count. A collection stops every
    thread of the process, whichever thread triggered it."""

    def __init__(self) -> None:
        self.total_s = 0.0
        self.count = 0
        self.longest_s = 0.0
        self.by_generation = [0, 0, 0]
        self.threads: dict[str, float] = {}  # thread name -> seconds it spent collecting
        self._start: float | None = None

    def __call__(self, phase: str, info: dict[str, Any]) -> None:
        now = time.perf_counter()
        if phase == "start":
            self._start = now
            return
        if self._start is None:
            return
        pause, self._start = now - self._start, None
        self.total_s += pause
        self.count += 1
        self.longest_s = max(self.longest_s, pause)
        generation = int(info.get("generation", 0))
        if 0 <= generation < len(self.by_generation):
            self.by_generation[generation] += 1
        name = threading.current_thread().name
        self.threads[name] = self.threads.get(name, 0.0) + pause

    def __enter__(self) -> GcPauses:
        gc.callbacks.append(self)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            gc.callbacks.remove(self)
        except ValueError:
            pass


class SchedStat:
    """The calling thread's CPU time and run-queue wait (ns) from Linux's schedstat, opened
    by the thread it reads (None where the file does not exist)."""

    def __init__(self) -> None:
        try:
            self._fd: int | None = os.open("/proc/thread-self/schedstat", os.O_RDONLY)
        except OSError:
            self._fd = None

    def read(self) -> tuple[float, float] | None:
        """(seconds on a CPU, seconds runnable and waiting for one), or None."""
        if self._fd is None:
            return None
        try:
            fields = os.pread(self._fd, 128, 0).split()
            return int(fields[0]) / 1e9, int(fields[1]) / 1e9
        except (OSError, ValueError, IndexError):
            return None

    def close(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


@dataclass(frozen=True)
class Gap:
    """One interval between two commands (wall seconds), and what filled it."""

    step: int  # the step whose command ended the gap
    t: float  # its loop time
    gap_s: float
    arm_wait_s: float  # waiting for the arm's state until the reader had it complete
    wake_s: float  # from the state complete at the reader to the loop holding it
    controller_s: float
    hook_s: float  # the step hook (recorder, viewer, live view) after the previous command
    gc_s: float  # garbage collection, any thread
    cpu_s: float  # the loop thread on a CPU
    runqueue_s: float | None  # the loop thread runnable, waiting for a CPU (None: unknown)
    reader_away_s: float = 0.0  # the longest the reader thread was away from the link
    reader_queued_s: float | None = None  # of which runnable, given no CPU (None: unknown)

    @property
    def process_stalled(self) -> bool:
        """The reader was away for most of the wait: this process was not running (no CPU,
        or the GIL held elsewhere), not the arm late."""
        return self.reader_away_s > 0.5 * max(self.arm_wait_s, 1e-9) and self.reader_away_s > 0.05

    @property
    def other_s(self) -> float:
        """What no part accounts for (checks, the command's write, the GIL, I/O)."""
        parts = self.arm_wait_s + self.wake_s + self.controller_s + self.hook_s
        return max(self.gap_s - parts, 0.0)

    def parts(self) -> dict[str, float]:
        """The gap's parts, largest first (the loop's own CPU and the run queue overlap the
        others, so they are named apart in `describe`)."""
        waiting = (
            "this process not running (the reader thread away too)"
            if self.process_stalled
            else "waiting for the arm's state"
        )
        named = {
            waiting: self.arm_wait_s,
            "waking for the state it had": self.wake_s,
            "the controller": self.controller_s,
            "the step hook (recorder, viewer, live view)": self.hook_s,
            "garbage collection": self.gc_s,
            "the rest (checks, writing the command)": self.other_s,
        }
        return dict(sorted(named.items(), key=lambda kv: -kv[1]))

    def cause(self) -> str:
        """The largest part, in a few words."""
        return next(iter(self.parts()))

    def describe(self) -> str:
        parts = ", ".join(f"{name} {ms(v)}" for name, v in self.parts().items() if v >= 0.0005)
        queue = (
            ""
            if self.runqueue_s is None
            else f", runnable but given no CPU for {ms(self.runqueue_s)}"
        )
        away = ""
        if self.reader_away_s >= 0.05:
            queued = self.reader_queued_s
            of = "" if queued is None else f" ({ms(queued)} of it runnable, given no CPU)"
            away = f"; the reader thread was away {ms(self.reader_away_s)}{of}"

        return (
            f"step {self.step} (t = {self.t:.2f} s) came {ms(self.gap_s)} after the previous "
            f"command: {parts or 'nothing measurable'}; the loop thread ran {ms(self.cpu_s)}"
            f"{queue}{away}"
        )

    def as_dict(self) -> dict[str, object]:
        return {
            "step": self.step,
            "t": self.t,
            "gap_s": self.gap_s,
            "arm_wait_s": self.arm_wait_s,
            "wake_s": self.wake_s,
            "controller_s": self.controller_s,
            "hook_s": self.hook_s,
            "gc_s": self.gc_s,
            "cpu_s": self.cpu_s,
            "runqueue_s": self.runqueue_s,
            "reader_away_s": self.reader_away_s,
            "reader_queued_s": self.reader_queued_s,
            "cause": self.cause(),
        }


def ms(seconds: float) -> str:
    return f"{seconds * 1e3:.1f} ms"


@dataclass(frozen=True)
class GapStats:
    """The gaps between commands over a run (wall seconds; NaN with fewer than two)."""

    count: int = 0
    p50_s: float = math.nan
    p99_s: float = math.nan
    p999_s: float = math.nan
    max_s: float = math.nan
    gc_pauses: int = 0
    gc_total_s: float = 0.0
    gc_longest_s: float = 0.0
    longest: tuple[Gap, ...] = field(default_factory=tuple)  # longest first

    def brief(self) -> str:
        """e.g. 'loop period p50 50.0 / p99 53.1 / p99.9 60.2 / max 61.0 ms'."""
        if not self.count:
            return "loop period not measured (fewer than two commands)"
        return (
            f"loop period p50 {self.p50_s * 1e3:.1f} / p99 {self.p99_s * 1e3:.1f} / p99.9 "
            f"{self.p999_s * 1e3:.1f} / max {self.max_s * 1e3:.1f} ms over {self.count} gaps"
        )


class GapLog:
    """The loop's side: parts are added as they happen (`add_*`), `command` closes a gap."""

    def __init__(self, reader_away: Callable[[], tuple[float, float | None]] | None = None) -> None:
        """`reader_away`: the longest the link's reader was away since last asked
        (`ArmClient.reader_away`)."""
        self._reader_away = reader_away
        self.gaps: list[float] = []
        self._kept: list[tuple[float, int, Gap]] = []  # a min-heap of the longest
        self._last: float | None = None
        self._arm_wait = self._wake = self._controller = self._hook = 0.0
        self._gc0 = 0.0
        self._cpu0 = 0.0
        self._queue0: float | None = None
        self.pauses = GcPauses()
        self._sched: SchedStat | None = None

    def start(self) -> None:
        """On the loop's thread, before the first step."""
        self._sched = SchedStat()
        self.pauses.__enter__()

    def stop(self) -> None:
        self.pauses.__exit__(None, None, None)
        if self._sched is not None:
            self._sched.close()

    def add_state_wait(self, waited_s: float, complete_t: float, got_t: float) -> None:
        """The loop waited `waited_s` for a state the reader completed at `complete_t` and
        the loop held at `got_t` (same clock)."""
        wake = min(max(got_t - complete_t, 0.0), waited_s) if math.isfinite(complete_t) else 0.0
        self._wake += wake
        self._arm_wait += waited_s - wake

    def add_controller(self, seconds: float) -> None:
        self._controller += seconds

    def add_hook(self, seconds: float) -> None:
        self._hook += seconds

    def in_gap(self, now: float) -> float:
        """How long since the last command (0 before the first)."""
        return 0.0 if self._last is None else now - self._last

    def _gap(self, now: float, step: int, t: float, cpu: float, queue: float | None) -> Gap:
        assert self._last is not None
        away, queued = self._reader_away() if self._reader_away is not None else (0.0, None)
        return Gap(
            step=step,
            t=t,
            gap_s=now - self._last,
            arm_wait_s=self._arm_wait,
            wake_s=self._wake,
            controller_s=self._controller,
            hook_s=self._hook,
            gc_s=self.pauses.total_s - self._gc0,
            cpu_s=cpu - self._cpu0,
            runqueue_s=None if queue is None or self._queue0 is None else queue - self._queue0,
            reader_away_s=away,
            reader_queued_s=queued,
        )

    def _keep(self, entry: Gap) -> None:
        item = (entry.gap_s, entry.step, entry)
        if len(self._kept) < KEPT_GAPS:
            heapq.heappush(self._kept, item)
        elif entry.gap_s > self._kept[0][0]:
            heapq.heapreplace(self._kept, item)

    def pending(self, now: float, step: int, t: float) -> Gap | None:
        """The gap still open at `now` (a command that could not go out), taken apart and
        kept among the longest; None before the first command."""
        if self._last is None:
            return None
        sched = self._sched.read() if self._sched is not None else None
        entry = self._gap(now, step, t, time.thread_time(), None if sched is None else sched[1])
        self._keep(entry)
        return entry

    def command(self, now: float, step: int, t: float) -> None:
        """A command went out at `now`: the gap since the previous one is closed."""
        cpu = time.thread_time()
        sched = self._sched.read() if self._sched is not None else None
        queue = None if sched is None else sched[1]
        if self._last is not None:
            entry = self._gap(now, step, t, cpu, queue)
            self.gaps.append(entry.gap_s)
            self._keep(entry)
        elif self._reader_away is not None:
            self._reader_away()  # counted from the first command on
        self._last = now
        self._arm_wait = self._wake = self._controller = self._hook = 0.0
        self._gc0 = self.pauses.total_s
        self._cpu0 = cpu
        self._queue0 = queue

    def timing(self, nominal_s: float, without_realtime: str | None = None) -> LoopTiming | None:
        """The loop's timing so far, for the watchdog's message (any thread); None before
        two commands unless it runs `without_realtime` (why), which a trip names."""
        gaps = list(self.gaps)
        if not gaps:
            if without_realtime is None:
                return None
            return LoopTiming(nominal_s, math.nan, math.nan, 0, without_realtime)
        p99 = float(np.percentile(gaps, 99))
        return LoopTiming(nominal_s, p99, max(gaps), len(gaps), without_realtime)

    def stats(self) -> GapStats:
        if not self.gaps:
            return GapStats(
                gc_pauses=self.pauses.count,
                gc_total_s=self.pauses.total_s,
                gc_longest_s=self.pauses.longest_s,
            )
        gaps = np.asarray(self.gaps)
        p50, p99, p999 = np.percentile(gaps, [50, 99, 99.9])
        return GapStats(
            count=len(gaps),
            p50_s=float(p50),
            p99_s=float(p99),
            p999_s=float(p999),
            max_s=float(gaps.max()),
            gc_pauses=self.pauses.count,
            gc_total_s=self.pauses.total_s,
            gc_longest_s=self.pauses.longest_s,
            longest=tuple(g for _, _, g in sorted(self._kept, key=lambda k: -k[0])),
        )
