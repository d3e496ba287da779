"""Real-time priority for the threads a command waits on: the control loop and the link's reader.

On a busy host the OS can give the whole driver no CPU for longer than the watchdog
(docs/reliability.md, 46-2); a SCHED_FIFO thread runs before every ordinary one, as robot
drivers run their control threads where permitted (libfranka's RealtimeConfig, ros2_control).
Linux applies a scheduling policy to one thread, so each thread asks for it itself
(`os.sched_setscheduler(0, ...)`), with SCHED_RESET_ON_FORK so that threads and processes it
starts (the recorder's writer, a viewer) stay ordinary. A thread already real-time at the
priority asked or above (`chrt -f 20 reach-driver ...`) keeps its own.

The policy (`run --realtime`): TRY asks and goes on without it, and the run's summary says why;
REQUIRE refuses the run before anything is commanded (`RealtimeRefusedError`); OFF never asks.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from enum import Enum

log = logging.getLogger(__name__)

#: SCHED_FIFO priority asked for (1..99): above every ordinary thread, below the kernel's own
#: real-time threads (interrupt threads run at 50).
DEFAULT_PRIORITY = 10

#: How long the control loop waits for the reader's outcome; the reader asks as the first
#: thing it does, long before a run can start (the connect's requests need it).
READER_WAIT_S = 5.0


class RealtimePolicy(str, Enum):
    TRY = "try"
    REQUIRE = "require"
    OFF = "off"


class RealtimeStatus(str, Enum):
    GRANTED = "granted"
    NOT_PERMITTED = "not permitted"
    NOT_SUPPORTED = "not supported"
    NOT_ASKED = "not asked"  # the policy is OFF, or the thread started before it was set


class ThreadRole(str, Enum):
    LOOP = "control loop"
    READER = "link reader"


@dataclass(frozen=True)
class RealtimeOutcome:
    """What one thread was given."""

    role: ThreadRole
    status: RealtimeStatus
    priority: int = 0  # the SCHED_FIFO (or RR) priority it runs at when granted
    reason: str = ""  # why it was not granted

    @property
    def granted(self) -> bool:
        return self.status is RealtimeStatus.GRANTED

    def describe(self) -> str:
        if self.granted:
            return f"{self.role.value}: SCHED_FIFO {self.priority}"
        return f"{self.role.value}: {self.status.value}" + (
            f" ({self.reason})" if self.reason else ""
        )


@dataclass(frozen=True)
class RealtimeReport:
    """The run's threads and what each was given, under `policy`."""

    policy: RealtimePolicy = RealtimePolicy.OFF
    outcomes: tuple[RealtimeOutcome, ...] = ()

    @property
    def granted(self) -> bool:
        return bool(self.outcomes) and all(o.granted for o in self.outcomes)

    def without(self) -> str | None:
        """Why the run goes without real-time priority (None when every thread has it, or it
        was not asked for)."""
        if self.policy is RealtimePolicy.OFF or self.granted:
            return None
        missing = [o for o in self.outcomes if not o.granted]
        if not missing:
            return None
        said: dict[tuple[RealtimeStatus, str], list[str]] = {}
        for o in missing:  # the usual case: every thread refused alike, said once
            said.setdefault((o.status, o.reason), []).append(o.role.value)
        return "; ".join(
            f"{status.value} for the {' and the '.join(roles)}" + (f": {reason}" if reason else "")
            for (status, reason), roles in said.items()
        )

    def refusal(self) -> str | None:
        """Under REQUIRE, the one line a refused run ends with; None when it may go on."""
        why = self.without()
        if self.policy is not RealtimePolicy.REQUIRE or why is None:
            return None
        return f"real-time priority required but {why}; nothing was commanded"

    def describe(self) -> str:
        """One phrase for the run's summary."""
        if self.policy is RealtimePolicy.OFF:
            return "real-time priority not asked for (off)"
        why = self.without()
        if why is not None:
            return f"without real-time priority: {why}"
        levels = {o.priority for o in self.outcomes}
        if len(levels) == 1:
            roles = ", ".join(o.role.value for o in self.outcomes)
            return f"real-time priority SCHED_FIFO {levels.pop()} ({roles})"
        return "real-time priority: " + ", ".join(o.describe() for o in self.outcomes)

    def as_dict(self) -> dict[str, object]:
        return {
            "policy": self.policy.value,
            "granted": self.granted,
            "without": self.without(),
            "threads": {
                o.role.value: {"status": o.status.value, "priority": o.priority, "reason": o.reason}
                for o in self.outcomes
            },
        }


def _fifo() -> int:
    return int(os.SCHED_FIFO) | int(getattr(os, "SCHED_RESET_ON_FORK", 0))


def _rtprio_limit() -> str:
    try:
        import resource
    except ImportError:
        return "unknown"
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


#: CAP_SYS_NICE's bit in /proc/self/status's CapEff.
CAP_SYS_NICE = 23


def _has_sys_nice() -> bool | None:
    """Whether this process holds CAP_SYS_NICE (None where Linux does not say)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> CAP_SYS_NICE & 1)
    except (OSError, ValueError, IndexError):
        pass
    return None


def not_permitted_reason(priority: int) -> str:
    """Why the kernel refused SCHED_FIFO `priority` to this process, and what grants it."""
    if _has_sys_nice():
        return (
            "refused although this process has CAP_SYS_NICE: its control group gives "
            "real-time threads no CPU time (cpu.rt_runtime_us)"
        )
    return (
        f"needs CAP_SYS_NICE or an rtprio limit of at least {priority} "
        f"(`ulimit -r` is {_rtprio_limit()})"
    )


def ask(role: ThreadRole, priority: int = DEFAULT_PRIORITY) -> RealtimeOutcome:
    """SCHED_FIFO `priority` for the calling thread (see the module docstring)."""
    if not hasattr(os, "sched_setscheduler") or not hasattr(os, "SCHED_FIFO"):
        return RealtimeOutcome(role, RealtimeStatus.NOT_SUPPORTED, reason="not on this OS")
    try:
        policy = os.sched_getscheduler(0) & ~int(getattr(os, "SCHED_RESET_ON_FORK", 0))
        if policy in (os.SCHED_FIFO, os.SCHED_RR):
            held = os.sched_getparam(0).sched_priority
            if held >= priority:
                return RealtimeOutcome(role, RealtimeStatus.GRANTED, held)
        os.sched_setscheduler(0, _fifo(), os.sched_param(priority))
    except PermissionError:
        return RealtimeOutcome(
            role, RealtimeStatus.NOT_PERMITTED, reason=not_permitted_reason(priority)
        )
    except OSError as exc:  # EINVAL: a priority or policy this kernel does not have
        return RealtimeOutcome(role, RealtimeStatus.NOT_SUPPORTED, reason=str(exc))
    return RealtimeOutcome(role, RealtimeStatus.GRANTED, priority)


class RealtimeThreads:
    """The real-time priority of one client's command path: the policy, and each thread's
    outcome as it asked (the reader's from the reader, the loop's from the loop)."""

    def __init__(
        self, policy: RealtimePolicy = RealtimePolicy.OFF, priority: int = DEFAULT_PRIORITY
    ) -> None:
        self.policy = RealtimePolicy(policy)
        self.priority = priority
        self._changed = threading.Condition()
        self._outcomes: dict[ThreadRole, RealtimeOutcome] = {}
        self._expected: set[ThreadRole] = set()

    def enter(self, role: ThreadRole) -> RealtimeOutcome:
        """In the thread taking `role`: ask as the policy says, keep the outcome."""
        if self.policy is RealtimePolicy.OFF:
            outcome = RealtimeOutcome(role, RealtimeStatus.NOT_ASKED)
        else:
            outcome = ask(role, self.priority)
        with self._changed:
            self._outcomes[role] = outcome
            self._changed.notify_all()
        return outcome

    def thread_target(self, role: ThreadRole, target: Callable[[], None]) -> Callable[[], None]:
        """`target` for a new thread that first takes `role` (called where it is started)."""
        with self._changed:
            self._expected.add(role)
            self._outcomes.pop(role, None)

        def run() -> None:
            self.enter(role)
            target()

        return run

    @contextmanager
    def held(self, role: ThreadRole) -> Iterator[RealtimeOutcome]:
        """The calling thread takes `role` within, and gets its own scheduling back after."""
        before = _current()
        outcome = self.enter(role)
        try:
            yield outcome
        finally:
            if outcome.granted and before is not None and _current() != before:
                _restore(role, *before)

    def outcome(self, role: ThreadRole, timeout_s: float = READER_WAIT_S) -> RealtimeOutcome:
        """`role`'s outcome, waited for while a thread started to take it has not asked yet."""
        with self._changed:
            if role in self._expected:
                self._changed.wait_for(lambda: role in self._outcomes, timeout_s)
            got = self._outcomes.get(role)
        if got is not None:
            return got
        why = (
            "its thread did not ask in time"
            if role in self._expected
            else "its thread started before this policy was set"
        )
        return RealtimeOutcome(role, RealtimeStatus.NOT_ASKED, reason=why)

    def report(self, *roles: ThreadRole) -> RealtimeReport:
        """The outcomes of `roles` (default: every role), under the policy."""
        return RealtimeReport(
            self.policy, tuple(self.outcome(r) for r in roles or tuple(ThreadRole))
        )


def _current() -> tuple[int, int] | None:
    """The calling thread's scheduling policy (flags included) and priority, if known."""
    if not hasattr(os, "sched_getscheduler"):
        return None
    try:
        return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    except OSError:
        return None


def _restore(role: ThreadRole, policy: int, priority: int) -> None:
    """Give the calling thread `policy` and `priority` back (SCHED_RESET_ON_FORK stays set
    where this thread may not clear it: without CAP_SYS_NICE)."""
    reset = int(getattr(os, "SCHED_RESET_ON_FORK", 0))
    for flags in (policy, policy | reset):
        try:
            os.sched_setscheduler(0, flags, os.sched_param(priority))
            return
        except PermissionError:
            continue
        except OSError as exc:
            log.warning("could not give the %s its scheduling back: %s", role.value, exc)
            return
    log.warning("could not give the %s its scheduling back: not permitted", role.value)
