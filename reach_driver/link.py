"""Link supervision settings, states, the events the client reports (link, watchdog, faults)
and their history, and its counters."""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum


class LinkState(str, Enum):
    UP = "up"  # packets flowing; commands are sent
    DOWN = "down"  # lost; the transport is closed and will be reopened after a backoff
    PROBING = "probing"  # reopened, waiting for the arm to answer before commands resume
    CLOSED = "closed"  # the client was closed
    FAILED = "failed"  # a different arm answered after a reconnect: nothing is sent to it


class EventKind(str, Enum):
    LINK_DOWN = "link down"
    LINK_UP = "link up"
    RECONNECT_FAILED = "reconnect failed"
    WATCHDOG = "watchdog"
    FAULT = "fault"
    FAULT_CLEARED = "fault cleared"
    IDENTITY = "different arm"
    LIMITS_REJECTED = "limits rejected"
    IMPLAUSIBLE = "implausible feedback"


@dataclass(frozen=True)
class ClientEvent:
    """Something a person watching the arm should hear about (the CLI prints these)."""

    kind: EventKind
    t: float
    message: str
    device: int | None = None


EventCallback = Callable[[ClientEvent], None]

#: How many of its latest events a client keeps (`ArmClient.events`).
EVENT_HISTORY = 200


class EventHistory:
    """A client's events: the latest kept, each logged (to the client's logger) and passed to
    every callback; a callback that fails is logged, and the others still get the event."""

    def __init__(self, clock: Callable[[], float], log: logging.Logger) -> None:
        self.kept: deque[ClientEvent] = deque(maxlen=EVENT_HISTORY)
        self.callbacks: list[EventCallback] = []
        self._clock = clock
        self._log = log

    def emit(self, kind: EventKind, message: str, device: int | None = None) -> None:
        event = ClientEvent(kind, self._clock(), message, device)
        self.kept.append(event)
        quiet = kind in (EventKind.LINK_UP, EventKind.FAULT_CLEARED)
        level = logging.INFO if quiet else logging.WARNING
        self._log.log(level, "%s: %s", kind.value, message)
        for callback in list(self.callbacks):
            try:
                callback(event)
            except Exception:
                self._log.exception("event callback %r failed", callback)


@dataclass(frozen=True)
class LinkConfig:
    """When silence means a lost link, and how reconnecting backs off.

    A keepalive REQUEST goes out after `keepalive_s` without a valid packet, so a healthy
    arm is never silent for `stale_link_s`; UDP and CAN have no other way to tell.
    """

    stale_link_s: float = 1.0
    keepalive_s: float = 0.25
    probe_timeout_s: float = 0.5
    backoff_initial_s: float = 0.1
    backoff_max_s: float = 2.0
    reconnect: bool = True

    def __post_init__(self) -> None:
        if not 0 < self.keepalive_s < self.stale_link_s:
            raise ValueError("need 0 < keepalive_s < stale_link_s")
        if not 0 < self.backoff_initial_s <= self.backoff_max_s:
            raise ValueError("need 0 < backoff_initial_s <= backoff_max_s")


class Backoff:
    """Doubling delays between reconnect attempts, capped, reset on success."""

    def __init__(self, initial_s: float, max_s: float) -> None:
        self.initial_s = initial_s
        self.max_s = max_s
        self.attempt = 0

    def next_delay(self) -> float:
        delay = min(self.max_s, self.initial_s * (2.0**self.attempt))
        self.attempt += 1
        return delay

    def reset(self) -> None:
        self.attempt = 0


@dataclass
class ClientStats:
    """Counters for the monitor and for tests (link errors are in transport/decoder stats)."""

    packets: int = 0
    requests_sent: int = 0
    request_retries: int = 0
    request_timeouts: int = 0
    link_drops: int = 0
    reconnects: int = 0
    watchdog_trips: int = 0
    keepalives: int = 0
    identity_mismatches: int = 0
    limits_rejected: int = 0  # limits the arm reported that safety did not adopt
