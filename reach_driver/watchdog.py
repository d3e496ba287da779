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
from dataclasses import dataclass

from protocol import Mode, Packet, PacketID
from reach_driver.state import joint_name

#: Commands that arm a joint: it follows them until told otherwise.
CONTINUOUS_PACKETS = frozenset({PacketID.VELOCITY, PacketID.CURRENT})
CONTINUOUS_MODES = frozenset({Mode.VELOCITY, Mode.CURRENT})

#: When a device's feedback last arrived (None if never): a time, or (time, quantity) for the
#: stalest of the quantities a controller uses (position, velocity), so a trip names it.
FeedbackTime = Callable[[int], "float | tuple[float | None, str] | None"]

#: A control loop commands once a period and reads the arm once a period: the watchdog must
#: span this many periods, so that one late or lost tick does not trip it. Raising the
#: watchdog to follow a long period would let a stalled controller's last current run that
#: long unnoticed, so a period it cannot span is refused instead (`watchdog_too_short`).
WATCHDOG_PERIODS = 2.0
#: The option a person sets the limit with; the CLI shows it in place of the API's name.
LIMIT_NAME = "SafetyConfig.watchdog_s"


@dataclass(frozen=True)
class LoopTiming:
    """How a running control loop has kept time so far (wall seconds between commands)."""

    nominal_s: float
    p99_s: float
    max_s: float
    gaps: int
    #: Why the loop runs without real-time priority (None: it has it, or was not to ask).
    without_realtime: str | None = None

    @property
    def busy(self) -> bool:
        """The loop has been late often enough to show in its p99: the host is busy."""
        return self.gaps >= 20 and self.p99_s > BUSY_P99 * self.nominal_s

    def describe(self) -> str:
        return (
            f"p99 {self.p99_s * 1e3:.1f} ms, max {self.max_s * 1e3:.1f} ms over {self.gaps} "
            f"periods of {self.nominal_s * 1e3:.0f} ms"
        )


#: A loop period p99 this many times the nominal one means a busy host.
BUSY_P99 = 1.2


def watchdog_too_short(period_s: float, watchdog_s: float | None) -> str | None:
    """Why a loop at `period_s` cannot run under a `watchdog_s` watchdog, or None if it can."""
    if watchdog_s is None or watchdog_s >= WATCHDOG_PERIODS * period_s * (1 - 1e-9):
        return None
    need = WATCHDOG_PERIODS * period_s
    return (
        f"a {period_s:g} s control period needs a watchdog of at least {need:g} s (two "
        f"periods, so one late or lost tick does not trip it), but {LIMIT_NAME} is "
        f"{watchdog_s:g} s: the watchdog would trip between two commands. Give a shorter "
        f"period, or a longer watchdog ({LIMIT_NAME} {need:g}) if a stalled controller's last "
        f"command may run that long"
    )


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
        self,
        now: float,
        limit_s: float | None,
        feedback_t: FeedbackTime,
        away_s: float = 0.0,
        loop: LoopTiming | None = None,
    ) -> tuple[str, tuple[int, ...]] | None:
        """(why, armed devices) if commands or feedback are older than `limit_s`, else None.

        Stale feedback is named first: a loop paced by the arm's state stops commanding when
        the state stops, so "no command" alone would blame the controller for the link.
        `away_s`: how long the checking (reader) thread had been away before `now`; when that
        is most of the limit, this process was not running at all, and the trip says so
        rather than blame the controller or the arm. `loop`: the running loop's timing, named
        in a "no command" trip so a busy machine shows as one."""
        with self._lock:
            armed = dict(self._armed)
            last_command = self._last_command_t
        if limit_s is None or not armed:
            return None
        limit = f"watchdog {limit_s:g} s, {LIMIT_NAME}"
        silent = now - last_command
        stalled = away_s > limit_s / 2
        why = None if loop is None else loop.without_realtime

        # a busy machine is the OS's choice of thread: a loop without real-time priority says so
        def busy(timing: str = "") -> str:
            grant = f"; real-time priority was not granted: {why}" if why else ""
            return f"the machine was busy{timing}{grant}"

        process = (
            f"; this process itself had not run for {away_s:.3f} s ({busy()}; "
            f"raise {LIMIT_NAME} or reduce the load)"
            if stalled
            else ""
        )
        for dev, since in armed.items():
            got = feedback_t(dev)
            fed, quantity = (got[0], f" {got[1]}") if isinstance(got, tuple) else (got, "")
            last = max(since, fed if fed is not None else -math.inf)
            if now - last > limit_s:
                also = (
                    f"; no command for {silent:.3f} s either (a loop waits for the arm's state)"
                    if silent > limit_s
                    else ""
                )
                reason = (
                    f"feedback from {joint_name(dev)}{quantity} stale for {now - last:.3f} s "
                    f"({limit})"
                    f"{also}: the feedback stopped (the arm stopped reporting, the link is "
                    f"failing, or the arm reset){process}"
                )
                return reason, tuple(armed)
        if silent > limit_s:
            head = f"no command for {silent:.3f} s ({limit})"
            timing = "" if loop is None or not loop.gaps else f" (loop period {loop.describe()})"
            if stalled:
                reason = (
                    f"{head}: this process did not run for {away_s:.3f} s of it, its reader "
                    f"thread no more than the controller: {busy(timing)}; raise "
                    f"{LIMIT_NAME} or reduce the load"
                )
            elif loop is not None and loop.busy:
                reason = (
                    f"{head} while the arm's feedback kept arriving: the controller did not "
                    f"command for {silent:.3f} s: {busy(timing)}; raise "
                    f"{LIMIT_NAME} or reduce the load"
                )
            else:
                reason = (
                    f"{head} while the arm's feedback kept arriving: the controller did not "
                    f"command{timing} (a stalled or slow controller, a busy machine, or a "
                    f"control period near the watchdog: raise {LIMIT_NAME} or reduce the load)"
                )
            return reason, tuple(armed)
        return None

    def trip(self, reason: str) -> None:
        with self._lock:
            self._tripped = reason
            self._armed.clear()

    def explain(self, reason: str) -> bool:
        """Replace the reason of a trip with a better-founded one (learnt after it); False if
        it is no longer tripped."""
        with self._lock:
            if self._tripped is None:
                return False
            self._tripped = reason
            return True

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
