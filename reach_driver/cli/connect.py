"""From parsed options to a started `ArmClient` (events and warnings to stderr)."""

from __future__ import annotations

import argparse
import logging
import math
import time
from collections.abc import Callable

from rich.console import Console
from rich.markup import escape

from protocol.models import ALPHA5
from reach_driver.chatter import ChatterConfig, HoldMode
from reach_driver.cli.arms import (
    current_values,
    currents_by_device,
    currents_problem,
    given_model,
    in_scope,
)
from reach_driver.cli.exits import UsageError, for_operator
from reach_driver.client import ArmClient
from reach_driver.errors import ArmModelError, BadUrlError
from reach_driver.identity import ModelCheck, device_list
from reach_driver.interfaces import open_transport
from reach_driver.link import ClientEvent, EventKind
from reach_driver.realtime import RealtimePolicy, RealtimeThreads
from reach_driver.safety import SafetyConfig

log = logging.getLogger("reach_driver.cli.events")  # to --log-file; the console shows them


def connect(args: argparse.Namespace, console: Console) -> ArmClient:
    if not args.port:
        raise BadUrlError(
            "no port: give --port (device, pyserial URL or udp://HOST) or set $REACH_PORT"
        )
    safety = safety_config(args)  # checked by main() already
    given = given_model(args)
    transport = open_transport(args.port, baud=args.baud, rs485=args.rs485)
    client = ArmClient(
        transport,
        safety=safety,
        request_timeout_s=args.timeout,
        retries=args.retries,
        model=given or ALPHA5,
    )
    # `run --realtime`: its reader asks as it starts; other commands never ask
    client.realtime = RealtimeThreads(RealtimePolicy(getattr(args, "realtime", "off")))

    # Events and warnings go to stderr so `info --json` stays parseable.
    notes = Console(stderr=True, highlight=False)
    client.on_event(EventPrinter(notes))
    try:
        client.start(model_check=ModelCheck.DETECT if given is None else ModelCheck.CONFIRM)
    except ArmModelError as exc:
        which = f"--arm {exc.answering}" if exc.answering else "the --arm of the arm that answers"
        raise ArmModelError(
            f"{exc}; give {which}, or leave --arm out to take the arm that answers",
            exc.answering,
        ) from None
    currents = current_values(args.max_current)
    problem = (
        currents_problem(currents, (client.model,), f"the {client.model.title}")
        if currents
        else None
    )
    if problem is not None:
        client.close()
        raise UsageError(f"{problem}; nothing was sent")
    if given is None and client.model is not ALPHA5:
        log.info("arm: %s (%s answer)", client.model.title, device_list(client.answering))
        notes.print(
            f"arm: {escape(client.model.title)} ({escape(device_list(client.answering))} answer)",
            soft_wrap=True,
        )
    for warning in client.warnings:
        log.warning("%s", warning)
        notes.print(f"[yellow]warning[/]: {escape(warning)}")
    return client


class EventPrinter:
    """Prints client events, the arm's text escaped (`[MOTOR_OVER_TEMP]` is not markup). A
    flapping status flag can raise thousands of fault events a second: the same fault line
    (kind, device, text) is printed at most once per `interval_s`, and the next one printed
    says how many were held back."""

    RATE_LIMITED = frozenset({EventKind.FAULT, EventKind.FAULT_CLEARED})

    def __init__(
        self,
        console: Console,
        clock: Callable[[], float] = time.monotonic,
        interval_s: float = 1.0,
    ) -> None:
        self.console = console
        self.clock = clock
        self.interval_s = interval_s
        self._last: dict[tuple[str, int | None, str], float] = {}
        self._held: dict[tuple[str, int | None, str], int] = {}

    def __call__(self, event: ClientEvent) -> None:
        style = "green" if event.kind in (EventKind.LINK_UP, EventKind.FAULT_CLEARED) else "red"
        suffix = ""
        if event.kind in self.RATE_LIMITED:
            key = (event.kind.value, event.device, event.message)
            now = self.clock()
            last = self._last.get(key)
            if last is not None and now - last < self.interval_s:
                self._held[key] = self._held.get(key, 0) + 1
                return
            self._last[key] = now
            held = self._held.pop(key, 0)
            if held and last is not None:
                suffix = f" ({held} more like this in the last {now - last:.1f} s, not shown)"
        message = for_operator(event.message)
        log.info("%s: %s%s", event.kind.value, message, suffix)
        self.console.print(
            f"[{style}]{event.kind.value}[/]: {escape(message)}{suffix}", soft_wrap=True
        )


def safety_config(args: argparse.Namespace) -> SafetyConfig:
    """The safety options as a config for whichever model of those in scope the arm is
    (`reach_driver.cli.arms`); ValueError for a bad value."""
    models = in_scope(args)
    given = current_values(args.max_current)
    problem = currents_problem(given, models) if given else None
    if problem is not None:
        raise ValueError(problem)
    currents = currents_by_device(given, models)
    if not (math.isfinite(args.position_margin) and args.position_margin >= 0):
        raise ValueError(f"--position-margin must be >= 0 rad, got {args.position_margin}")
    return SafetyConfig(
        watchdog_s=args.watchdog,
        current_limits_mA=currents,
        position_margin=args.position_margin,
        chatter=ChatterConfig(hold=HoldMode(args.chatter_hold)) if args.chatter_guard else None,
        safe_wait_s=args.safe_wait,
    )
