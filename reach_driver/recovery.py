"""What losing and regaining the link means for a client's requests, commands and watchdog;
the supervisor (`reach_driver.supervisor`) keeps only the link's state and timers.

Lost: every waiting request fails at once, and joints that were armed (obeying a velocity or
current) trip the watchdog and owe the safe mode. Reopened: with an identity on record
(`ArmClient.start`), the link stays PROBING until every device confirmed it is the same arm
(`IdentityCheck`); then the owed safe mode and the stream go out and the link is UP again.
A different arm gets only its safe mode, and the link is FAILED for good
(`ArmIdentityError`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

from protocol import Packet
from reach_driver.errors import ArmIdentityError, LinkDownError
from reach_driver.identity import DeviceIdentity, IdentityCheck
from reach_driver.link import ClientStats, EventKind, LinkState
from reach_driver.requests import Waiters
from reach_driver.safety import SafetyGuard
from reach_driver.state import StateTable
from reach_driver.streaming import Stream
from reach_driver.supervisor import LinkSupervisor
from reach_driver.watchdog import Watchdog


class LinkRecovery:
    """One client's side of a lost and reopened link (see the module docstring)."""

    def __init__(
        self,
        supervisor: LinkSupervisor,
        watchdog: Watchdog,
        waiters: Waiters,
        table: StateTable,
        stats: ClientStats,
        *,
        identity: dict[int, DeviceIdentity],
        lock: threading.RLock,
        stop: threading.Event,
        emit: Callable[[EventKind, str], None],
        send_internal: Callable[[Sequence[bytes]], object],
        guard: Callable[[], SafetyGuard],
        safe_frames: Callable[[Sequence[int]], list[bytes]],
        stream: Callable[[], Stream | None],
    ) -> None:
        self._supervisor = supervisor
        self._watchdog = watchdog
        self._waiters = waiters
        self._table = table
        self._stats = stats
        self._identity = identity  # what each device reported at connect (the client's)
        self._lock = lock  # the client's: link state and the watchdog change together
        self._stop = stop
        self._emit = emit
        self._send_internal = send_internal  # raises LinkDownError
        self._guard = guard  # the safety config and the model in force
        self._safe_frames = safe_frames
        self._stream = stream
        self._url = supervisor.transport.url
        self._check: IdentityCheck | None = None  # reader thread only

    def lost(self, reason: str) -> None:
        """Mark the link down (any thread); the reader thread reopens it."""
        with self._lock:
            was_up = self._supervisor.mark_down(reason)
            if was_up is None:
                return
            # Feedback is gone while joints obey the last velocity/current: the same as
            # stale feedback. The safe mode goes out first thing after reconnecting.
            armed = self._watchdog.trip_on_link_loss()  # owes the safe mode if armed
        self._waiters.fail_all(lambda: LinkDownError(self._supervisor.down_message()))
        if was_up:
            self._stats.link_drops += 1
            self._emit(EventKind.LINK_DOWN, f"{self._url}: {reason}")
            if armed:
                self._stats.watchdog_trips += 1
                self._emit(
                    EventKind.WATCHDOG,
                    f"{self._watchdog.tripped}; {self._guard().config.safe_mode.name} goes out "
                    "on reconnect",
                )
        if not self._supervisor.config.reconnect:
            self._stop.set()

    def reopened(self) -> None:
        """The supervisor reopened the link (reader thread): a fresh start for the check."""
        self._check = None

    def confirm(self, packet: Packet, t: float) -> bool:
        """While PROBING: True once the link is UP again and `packet` may be used. With an
        identity on record, the reopened link stays PROBING until every device confirmed it
        (its replies are not state); a difference fails the link at once."""
        if not self._identity:
            self._restored(t)
            return True
        check = self._check
        if check is None:
            self._check = check = IdentityCheck(self._identity)
            self._supervisor.extend_probe(t)
            try:
                self._send_internal(check.frames())
            except LinkDownError:
                pass
            return False
        check.offer(packet)
        if check.differences:
            self._failed(check.differences, t)
        elif check.complete:
            self._check = None
            self._restored(t)
        return False

    def _failed(self, differences: Sequence[str], t: float) -> None:
        """A different arm answers: stop it, send it nothing else, fail the link for good."""
        self._check = None
        guard = self._guard()
        mode = guard.config.safe_mode
        devices = guard.model.actuators
        try:
            self._send_internal(self._safe_frames(devices))
            sent = f"sent it {mode.name} and nothing else"
        except LinkDownError:
            sent = f"could not even send it {mode.name}"
        reason = (
            f"a different arm answers on {self._url}: {'; '.join(differences)}; "
            f"{sent}; close this client and start a new one to use that arm"
        )
        with self._lock:
            self._supervisor.set(LinkState.FAILED, reason, t)
            self._watchdog.disarm(devices)
            self._watchdog.take_safe_pending()
        self._table.clear()
        self._stats.identity_mismatches += 1
        self._waiters.fail_all(lambda: ArmIdentityError(self._supervisor.down_message()))
        self._emit(EventKind.IDENTITY, reason)

    def _restored(self, t: float) -> None:
        attempts = self._supervisor.restored(t)
        frames: list[bytes] = []
        owed = self._watchdog.take_safe_pending()
        if owed:
            frames += self._safe_frames(self._guard().model.actuators)
        stream = self._stream()
        if stream is not None:
            frames += stream.start_frames()
        if frames:
            try:
                self._send_internal(frames)
            except LinkDownError:
                if owed:
                    self._watchdog.mark_safe_pending()
                return
        self._emit(EventKind.LINK_UP, f"{self._url} answering again after {attempts} attempt(s)")
