"""Fan-out of received packets to subscribers, like python-can's Notifier and Listeners.

Listeners run on the reader thread, so they must be quick; `PacketQueue` hands packets to
another thread instead (like python-can's BufferedReader).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

from protocol import Packet

log = logging.getLogger(__name__)

PacketListener = Callable[[Packet, float], None]  # (packet, arrival time)


class ListenerSet:
    """The subscribers of one client; a failing listener is logged and counted, never fatal."""

    def __init__(self) -> None:
        self._listeners: tuple[PacketListener, ...] = ()
        self._lock = threading.Lock()
        self.errors = 0

    def add(self, listener: PacketListener) -> Subscription:
        with self._lock:
            self._listeners = (*self._listeners, listener)
        return Subscription(self, listener)

    def remove(self, listener: PacketListener) -> None:
        with self._lock:
            items = list(self._listeners)
            if listener in items:
                items.remove(listener)
            self._listeners = tuple(items)

    def __len__(self) -> int:
        return len(self._listeners)

    def dispatch(self, packet: Packet, t: float) -> None:
        for listener in self._listeners:  # a tuple: safe against (un)subscribing meanwhile
            try:
                listener(packet, t)
            except Exception:
                self.errors += 1
                log.exception("packet listener %r failed on %r", listener, packet)


class Subscription:
    """Returned by `subscribe`; `cancel()` (or leaving the `with` block) unsubscribes."""

    def __init__(self, owner: ListenerSet, listener: PacketListener) -> None:
        self._owner = owner
        self.listener = listener

    def cancel(self) -> None:
        self._owner.remove(self.listener)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()


class PacketQueue:
    """A listener that queues (packet, time) pairs for another thread, dropping the oldest
    when full so a slow consumer never stalls the reader."""

    def __init__(self, maxsize: int = 10000) -> None:
        self._queue: queue.Queue[tuple[Packet, float]] = queue.Queue(maxsize)
        self.dropped = 0
        self.subscription: Subscription | None = None

    def __call__(self, packet: Packet, t: float) -> None:
        while True:
            try:
                self._queue.put_nowait((packet, t))
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def get(self, timeout: float | None = None) -> tuple[Packet, float] | None:
        """The next packet, or None after `timeout` seconds without one."""
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def drain(self) -> list[tuple[Packet, float]]:
        out = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        if self.subscription is not None:
            self.subscription.cancel()
            self.subscription = None

    def __enter__(self) -> PacketQueue:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
