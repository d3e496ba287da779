"""The driver's exceptions: one base class so callers can catch everything the driver raises.

Each message names the port, joint or limit involved, because these errors end up in front
of someone holding a cable, not a debugger.
"""

from __future__ import annotations

import signal
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from reach_driver.records import ControlSummary


class DriverError(Exception):
    """Base of every error raised by `reach_driver`."""


class ExtraNotInstalledError(DriverError):
    """What was asked for needs an optional library that is not installed; the message names
    the extra that brings it (`protocol.extras`), e.g. pip install 'reach-stack[mpc]'."""

    def __init__(self, message: str, extra: str) -> None:
        super().__init__(message)
        self.extra = extra


class BadUrlError(DriverError, ValueError):
    """A `--port` string that names no transport we can open."""


class TransportError(DriverError):
    """Opening, reading or writing the link failed (cable out, port gone, socket error)."""


class PortNotFoundError(TransportError):
    """The serial device does not exist."""


class PortPermissionError(TransportError):
    """The serial device exists but this user may not open it."""


class PortBusyError(TransportError):
    """The serial device is held by another program (or another driver in this one)."""


class LinkDownError(DriverError):
    """A command was issued while the link is down; it was not sent."""


class ArmIdentityError(LinkDownError):
    """After a reconnect a different arm answered (serial or model number, or firmware
    version, differs from what was read at connect). Nothing but its safe stop was sent to
    it; the link stays failed: close the client and start a new one to use that arm."""


class ArmModelError(DriverError):
    """The devices answering at connect are another arm model's than the one named (or no
    known model's): nothing but REQUESTs was sent. `answering` names the model they are
    (its `ArmModel.name`), None for none known."""

    def __init__(self, message: str, answering: str | None = None) -> None:
        super().__init__(message)
        self.answering = answering


class RequestTimeoutError(DriverError, TimeoutError):
    """A device did not answer a REQUEST within its timeout and retries."""


class NoResponseError(DriverError):
    """Nothing on the link answers: wrong port, arm unpowered, or wrong address."""


class GarbageError(NoResponseError):
    """Bytes arrive but no valid frame decodes: most likely a wrong baud rate."""


class LimitError(DriverError, ValueError):
    """A command would leave a safety limit; it was refused and not sent."""


class WatchdogTrippedError(DriverError):
    """The watchdog put the arm in a safe mode; continuous commands wait for `rearm()`."""


class ArmFaultError(DriverError):
    """The arm reports hardware status flags (over current, encoder error, ...)."""


class ControllerError(DriverError):
    """A controller (or a per-step hook: a recorder, a viewer) raised or returned something
    other than 4 finite currents; the run ended there and the arm was put in its safe mode."""


class BadReadingError(DriverError):
    """The arm reported a value the control loop cannot use (NaN or Inf); the run ended
    before any controller saw it."""


class StreamRateError(DriverError):
    """The arm streams at another rate than the loop asked for (measured from its own
    kinematics, `reach_driver.stream_rate`): arm time and the controller's step would be
    wrong, so the run ends."""


class RealtimeRefusedError(DriverError):
    """Real-time priority was required (`RealtimePolicy.REQUIRE`) and a thread on the command
    path was not given it; raised before anything was commanded."""


class Interrupted(KeyboardInterrupt):
    """A signal asked the process to stop (SIGINT, SIGTERM, SIGHUP, SIGQUIT). A
    `KeyboardInterrupt`, so code that stops on Ctrl-C stops on these too; whatever was under
    way when it arrived fills in how it left the arm before passing it on: a control loop
    its `summary` (a `ControlSummary`), any other command `left_in`."""

    def __init__(
        self,
        signum: int = signal.SIGINT,
        *,
        summary: ControlSummary | None = None,
        left_in: str | None = None,
    ) -> None:
        super().__init__(signum)
        self.signum = int(signum)
        self.summary = summary
        self.left_in = left_in

    @property
    def signal_name(self) -> str:
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"
