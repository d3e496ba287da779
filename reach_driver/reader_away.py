"""How long the client's reader thread was away from the link between two reads.

A read waits at most the transport's read timeout, so a longer absence means this process
did not run (no CPU for the thread, or the GIL held elsewhere), not that the arm was late.
The watchdog names that as a trip's cause (a stalled process, not a stalled loop), the
stream diagnosis asks the arm nothing then, and a control loop's gap log reads the longest
absence (`ArmClient.reader_away`).
"""

from __future__ import annotations

from reach_driver.loop_timing import SchedStat


class ReaderAway:
    """When the reader thread last came back from a read and how long it had been away then;
    written by the reader thread only."""

    def __init__(self) -> None:
        self._t: float | None = None
        #: How long the reader had been away when it last came back.
        self.gap_s = 0.0
        self._max_s = 0.0  # the longest absence since `longest()` last asked
        self._queue_s: float | None = None  # of which runnable, given no CPU

    def came_back(self, now: float, sched: SchedStat, queue0: float | None) -> float | None:
        """The reader is back from a read at `now`. Keeps the longest absence, and how much
        of it this thread spent runnable but given no CPU (`sched`: this thread's run-queue
        time, `queue0`: its total at the last return); returns the run-queue total now."""
        self.gap_s = now - self._t if self._t is not None else 0.0
        self._t = now
        got = sched.read()
        queue = None if got is None else got[1]
        if self.gap_s > self._max_s:
            self._max_s = self.gap_s
            self._queue_s = None if queue is None or queue0 is None else queue - queue0
        return queue

    def longest(self) -> tuple[float, float | None]:
        """The longest absence since the last call, and how much of it the thread was
        runnable but given no CPU (None: unknown)."""
        away, self._max_s = self._max_s, 0.0
        return away, self._queue_s
