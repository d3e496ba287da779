"""Link supervision: when silence means the link is lost, keepalives, and reopening it.

UDP and CAN have no other way to tell a dead link, so a keepalive REQUEST goes out after
`LinkConfig.keepalive_s` without a valid packet and the link counts as lost after
`stale_link_s`. A lost link is closed and reopened with doubling delays; once reopened it is
PROBING until the arm answers, and only then UP again (commands resume). If the client
finds a different arm answering, it sets FAILED: terminal, never reopened.

The supervisor holds the link's state and timers and runs on the reader thread; what losing
or regaining the link means for commands, requests and the watchdog is `recovery`'s.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence

from reach_driver.errors import LinkDownError, TransportError
from reach_driver.link import Backoff, ClientStats, EventKind, LinkConfig, LinkState
from reach_driver.transport import Transport


class LinkSupervisor:
    def __init__(
        self,
        transport: Transport,
        config: LinkConfig,
        *,
        clock: Callable[[], float],
        stop: threading.Event,
        stats: ClientStats,
        emit: Callable[[EventKind, str], None],
        send_internal: Callable[[Sequence[bytes]], object],
        probe_frame: Callable[[], bytes],
        on_lost: Callable[[str], None],
        reset_decoder: Callable[[], None],
    ) -> None:
        self.transport = transport
        self.config = config
        self._clock = clock
        self._stop = stop
        self._stats = stats
        self._emit = emit
        self._send_internal = send_internal  # raises LinkDownError
        self._probe_frame = probe_frame
        self._on_lost = on_lost
        self._reset_decoder = reset_decoder
        self.state = LinkState.CLOSED
        self.reason = ""
        self.since = 0.0
        self.backoff = Backoff(config.backoff_initial_s, config.backoff_max_s)
        self._probe_deadline = 0.0
        self._last_packet_t = -math.inf
        self._last_keepalive_t = -math.inf
        self._contact = False

    def set(self, state: LinkState, reason: str, now: float) -> None:
        self.state = state
        self.reason = reason
        self.since = now

    def opened(self, now: float) -> None:
        self.set(LinkState.UP, "opened", now)
        self._last_packet_t = now

    def heard(self, t: float) -> bool:
        """A valid packet arrived; True if that ends PROBING (the caller restores the link)."""
        self._last_packet_t = t
        self._contact = True
        return self.state is LinkState.PROBING

    def mark_down(self, reason: str) -> bool | None:
        """Mark the link DOWN; whether it was UP, or None if it was already down or closed."""
        if self._stop.is_set() or self.state in (
            LinkState.DOWN,
            LinkState.CLOSED,
            LinkState.FAILED,
        ):
            return None
        was_up = self.state is LinkState.UP
        self.set(LinkState.DOWN, reason, self._clock())
        return was_up

    def extend_probe(self, now: float) -> None:
        """Something answered; give the client a full probe timeout to confirm the arm."""
        self._probe_deadline = now + self.config.probe_timeout_s

    def restored(self, t: float) -> int:
        """The arm answers again: UP. Returns how many reopening attempts it took."""
        attempts = self.backoff.attempt
        self.backoff.reset()
        self.set(LinkState.UP, "answering again", t)
        self._stats.reconnects += 1
        return attempts

    def down_message(self) -> str:
        url = self.transport.url
        if self.state is LinkState.FAILED:
            return f"link to {url} failed: {self.reason}; nothing was sent"
        if self.state is LinkState.CLOSED:
            why = f" ({self.reason})" if "crashed" in self.reason else ""
            return f"client for {url} is not running{why}; start() it first"
        age = self._clock() - self.since
        return (
            f"link to {url} is {self.state.value} since {age:.2f} s "
            f"({self.reason}); reconnecting, attempt {self.backoff.attempt}; "
            "nothing was sent"
        )

    def duties(self, now: float, while_up: Callable[[float], None]) -> None:
        """The reader thread's periodic work: give up on a silent reopened link, run
        `while_up` (the watchdog), notice a silent link, send keepalives."""
        cfg = self.config
        if self.state is LinkState.PROBING:
            if now > self._probe_deadline:
                self.transport.close()
                self.set(
                    LinkState.DOWN, f"no answer within {cfg.probe_timeout_s} s after reopening", now
                )
            return
        if self.state is not LinkState.UP:
            return
        while_up(now)
        silent = now - self._last_packet_t
        if self._contact and silent > cfg.stale_link_s:
            self._on_lost(f"no valid packet for {silent:.2f} s")
            return
        if (
            self._contact
            and silent > cfg.keepalive_s
            and now - self._last_keepalive_t > cfg.keepalive_s
        ):
            self._last_keepalive_t = now
            self._stats.keepalives += 1
            try:
                self._send_internal([self._probe_frame()])
            except LinkDownError:
                pass

    def reconnect_attempt(self) -> None:
        """Close, wait the next backoff delay, reopen and probe (reader thread, link DOWN)."""
        self.transport.close()
        delay = self.backoff.next_delay()
        if self._stop.wait(delay):
            return
        try:
            self.transport.open()
        except TransportError as exc:
            self.reason = str(exc)
            attempt = self.backoff.attempt
            if attempt in (1, 3, 10) or attempt % 30 == 0:
                self._emit(EventKind.RECONNECT_FAILED, f"attempt {attempt}: {exc}; retrying")
            return
        self._reset_decoder()
        now = self._clock()
        self._probe_deadline = now + self.config.probe_timeout_s
        self.set(LinkState.PROBING, "reopened, waiting for an answer", now)
        try:
            self._send_internal([self._probe_frame()])
        except LinkDownError:
            pass
