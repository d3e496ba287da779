"""Counting and rate-limited logging of events (bad frames, ignored commands).

A client spraying garbage must not flood the log, but every event must be counted and
each kind must show up in the log promptly.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable


class EventLog:
    """Counts events by reason; logs each reason at most once per `interval` wall seconds."""

    def __init__(
        self,
        logger: logging.Logger,
        level: int = logging.WARNING,
        interval: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.counts: Counter[str] = Counter()
        self._logger = logger
        self._level = level
        self._interval = interval
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def record(self, reason: str, message: str) -> None:
        self.counts[reason] += 1
        now = self._clock()
        last = self._last.get(reason)
        if last is not None and now - last < self._interval:
            self._suppressed[reason] += 1
            return
        self._last[reason] = now
        more = self._suppressed.pop(reason, 0)
        suffix = f" (+{more} more like it since the last report)" if more else ""
        self._logger.log(
            self._level, "%s: %s [%d so far]%s", reason, message, self.counts[reason], suffix
        )

    def snapshot(self) -> dict[str, int]:
        return dict(self.counts)
