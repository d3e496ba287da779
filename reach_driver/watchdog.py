"""Which joints are "armed" (obeying a velocity or current that must keep being refreshed),
and whether the watchdog tripped. This is the one place that decides it.

A joint in velocity or current mode keeps obeying its last command: if the host stops
commanding, or its feedback goes stale, it must be put in a safe mode. A position command,
or a mode other than velocity/current, makes that unnecessary again.

It also holds the "safe mode still owed" flag (set when a trip or a link loss could not send
it, taken when the link is back): set and taken from different threads, so under its lock,
and taken atomically so a loss noted meanwhile is never wiped.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable

from protocol import Mode, Packet, PacketID
from reach_driver.state import joint_name

#: Commands that arm a joint: it follows them until told otherwise.
CONTINUOUS_PACKETS = frozenset({PacketID.VELOCITY, PacketID.CURRENT})
CONTINUOUS_MODES = frozenset({Mode.VELOCITY, Mode.CURRENT})

#: When a device's position last arrived (None if never).
FeedbackTime = Callable[[int], "float | None"]


class Watchdog:
    """Thread-safe: commands note what they sent from the caller's thread, the reader thread
    checks the deadlines."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._armed: dict[int, float] = {}  # device -> when it was armed
        self._last_command_t = -math.inf
        self._tripped: str | None = None
        self._safe_pending = False

    @property
    def tripped(self) -> str | None:
        """Why it tripped, or None while it has not (or after `rearm()`)."""
        with self._lock:
            return self._tripped

    @property
    def armed(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(self._armed)

    def note_sent(self, packets: Iterable[Packet], now: float, *, disarm: bool = True) -> None:
        """Arm or disarm joints by what was just written to them (only arm, if not `disarm`)."""
        with self._lock:
            for p in packets:
                dev = int(p.device_id)
                if p.packet_id in CONTINUOUS_PACKETS:
                    self._last_command_t = now
                    self._armed.setdefault(dev, now)
                elif not disarm:
                    continue
                elif p.packet_id == PacketID.POSITION:
                    self._armed.pop(dev, None)
                elif p.packet_id == PacketID.MODE and p.data and p.data[0] not in CONTINUOUS_MODES:
                    self._armed.pop(dev, None)

    def disarm(self, devices: Iterable[int]) -> None:
        """The safe mode went out to these devices."""
        with self._lock:
            for d in devices:
                self._armed.pop(int(d), None)

    def expired(
        self, now: float, limit_s: float | None, feedback_t: FeedbackTime
    ) -> tuple[str, tuple[int, ...]] | None:
        """(why, armed devices) if commands or feedback are older than `limit_s`, else None."""
        with self._lock:
            armed = dict(self._armed)
            last_command = self._last_command_t
        if limit_s is None or not armed:
            return None
        if now - last_command > limit_s:
            return f"no command for {now - last_command:.3f} s (limit {limit_s} s)", tuple(armed)
        for dev, since in armed.items():
            fed = feedback_t(dev)
            last = max(since, fed if fed is not None else -math.inf)
            if now - last > limit_s:
                reason = (
                    f"feedback from {joint_name(dev)} stale for {now - last:.3f} s "
                    f"(limit {limit_s} s)"
                )
                return reason, tuple(armed)
        return None

    def trip(self, reason: str) -> None:
        with self._lock:
            self._tripped = reason
            self._armed.clear()

    def trip_on_link_loss(self) -> tuple[int, ...]:
        """With the feedback gone, armed joints obey their last command blind: trip and owe
        the safe mode (sent once the link is back). Returns the joints that were armed."""
        with self._lock:
            armed = tuple(self._armed)
            if armed:
                self._tripped = f"link lost while commanding {len(armed)} joint(s)"
                self._armed.clear()
                self._safe_pending = True
        return armed

    def mark_safe_pending(self) -> None:
        """The safe mode could not be sent: it goes out as soon as the link is back."""
        with self._lock:
            self._safe_pending = True

    def take_safe_pending(self) -> bool:
        """Whether the safe mode is owed, clearing it in the same step (one taker wins)."""
        with self._lock:
            pending, self._safe_pending = self._safe_pending, False
        return pending

    def rearm(self) -> None:
        with self._lock:
            self._tripped = None
