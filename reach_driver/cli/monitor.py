"""`monitor`: the arm's state, live, as a table or JSON lines; and the state stream that
`move` shares."""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console
from rich.live import Live

from protocol import PacketID
from reach_driver.cli.connect import connect
from reach_driver.cli.exits import (
    Exit,
    notes,
)
from reach_driver.cli.recorder import CliRecorder, check_record, kept_viewers
from reach_driver.cli.render import (
    monitor_json,
    monitor_line,
    monitor_table,
)
from reach_driver.cli.tables import fitted, show_table
from reach_driver.client import ArmClient
from reach_driver.errors import DriverError
from reach_driver.state import ArmState

if TYPE_CHECKING:
    pass


def cmd_monitor(args: argparse.Namespace, console: Console) -> Exit:
    check_record(args)
    client = connect(args, console)
    viewer = getattr(args, "viewer", None)
    recorder: CliRecorder | None = None
    stream: StateStream | None = None
    try:
        devices = client.found_devices
        ids = (PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT, PacketID.MODE)
        rate = client.stream(ids, args.rate, devices)
        if rate != args.rate:
            notes().print(
                f"[yellow]--rate {args.rate} Hz is more than the line carries for "
                f"{len(ids)} values of {len(devices)} devices: streaming at {rate} Hz[/yellow]"
            )
        read_diagnostics(client)  # the first table (and a recording) starts with them
        if viewer is not None or args.record:
            meta = {"command": "monitor", "port": args.port, "rate_hz": rate}
            recorder = CliRecorder(
                args.record,
                meta,
                viewer=viewer,
                diagnostics=lambda: client.state.joints,
                keep_into=kept_viewers(args),
                model=client.model,
            )
            stream = StateStream(client, recorder)
        # --seconds of watching, counted once the recording and the viewer are open: opening
        # them (loading rerun) takes seconds on a loaded host, which must not eat the window
        end = time.monotonic() + args.seconds if args.seconds else math.inf
        if args.json:
            return _monitor_json(client, console, end, stream)
        if not console.is_terminal:
            return _monitor_lines(client, console, args.port, end, stream)
        with Live(
            fitted(console, monitor_table(client, {}, args.port)),
            console=console,
            refresh_per_second=4,
            transient=False,
            auto_refresh=False,
        ) as live:
            try:
                for _, rates in _refreshes(client, end, stream, MONITOR_REFRESH_S):
                    table = monitor_table(client, rates, args.port)
                    live.update(fitted(console, table), refresh=True)
            except KeyboardInterrupt:
                pass  # Ctrl-C is how a monitor is meant to end: exit 0
        return Exit.OK
    except KeyboardInterrupt:
        return Exit.OK  # Ctrl-C before the first refresh ends a monitor just as well
    finally:
        if recorder is not None:
            if stream is not None:
                stream.last()  # the arm as the monitor ended
            recorder.close()
        client.close()


#: How often `monitor` refreshes (reads the Monitor readings, which a --record keeps, and
#: redraws its table or writes a --json line); piped, it writes a plain line every LINE_EVERY.
MONITOR_REFRESH_S = 0.5
MONITOR_LINE_EVERY = 2


def _refreshes(
    client: ArmClient, end: float, stream: StateStream | None, every_s: float
) -> Iterator[tuple[float, dict[tuple[int, int], float]]]:
    """Every `every_s` until `end` (wall clock): the time, and each (device, packet id)'s
    update rate (Hz) since the refresh before; the Monitor readings are read afresh each time."""
    last_counts = client.table.count_snapshot()
    last_t = time.monotonic()
    while time.monotonic() < end:
        wait_streaming(min(every_s, max(0.0, end - time.monotonic())), stream)
        now = time.monotonic()
        counts = client.table.count_snapshot()
        rates = {k: (n - last_counts.get(k, 0)) / (now - last_t) for k, n in counts.items()}
        last_counts, last_t = counts, now
        read_diagnostics(client)
        yield now, rates


def _monitor_lines(
    client: ArmClient, console: Console, port: str, end: float, stream: StateStream | None
) -> Exit:
    """`monitor` off a terminal (piped, redirected): a plain line a second, each flushed as
    it is written, then the table as it stands at the end."""
    start = time.monotonic()
    rates: dict[tuple[int, int], float] = {}
    try:
        refreshes = _refreshes(client, end, stream, MONITOR_REFRESH_S)
        for n, (now, rates) in enumerate(refreshes, start=1):
            if n % MONITOR_LINE_EVERY:
                continue
            console.out(monitor_line(client, rates, now - start), highlight=False)
            console.file.flush()  # a reader on a pipe gets each line as it comes
    except KeyboardInterrupt:
        pass  # Ctrl-C is how a monitor is meant to end: exit 0
    show_table(console, monitor_table(client, rates, port))
    return Exit.OK


class StateStream:
    """`monitor --viewer`, `move --viewer`: the arm's state to the viewer, at most 20 Hz."""

    PERIOD_S = 0.05
    FIRST_FULL_S = 1.0

    def __init__(
        self, client: ArmClient, recorder: CliRecorder, target: np.ndarray | None = None
    ) -> None:
        self.client, self.recorder, self.target = client, recorder, target
        self.t0 = time.monotonic()
        self.step = 0
        self._last = -math.inf

    def tick(self) -> None:
        now = time.monotonic()
        if now - self._last < self.PERIOD_S:
            return
        self._last = now
        self._log(now, self.client.state)

    def last(self, state: ArmState | None = None) -> None:
        """The state the command ended on (`state`, the one it judged; else the arm's latest),
        whenever the last tick was: the viewer's last frame is where the arm ended up."""
        now = time.monotonic()
        self._last = now
        self._log(now, state if state is not None else self.client.state)

    def _log(self, now: float, state: ArmState) -> None:
        seen = np.isfinite(state.q)
        if not np.any(seen) or (not np.all(seen) and now - self.t0 < self.FIRST_FULL_S):
            return  # wait for every joint's first angle (a joint that never answers: 1 s)
        self.recorder.on_state(
            now - self.t0, self.step, state.q, state.qdot, state.current, self.target
        )
        self.step += 1


def wait_streaming(
    seconds: float, stream: StateStream | None, stop: threading.Event | None = None
) -> None:
    """Sleep `seconds` (less once `stop` is set), feeding the viewer stream meanwhile if
    there is one."""
    stop = stop or threading.Event()
    if stream is None:
        stop.wait(seconds)
        return
    end = time.monotonic() + seconds
    while not stop.is_set():
        stream.tick()
        left = end - time.monotonic()
        if left <= 0:
            return
        stop.wait(min(stream.PERIOD_S, left))


def _monitor_json(
    client: ArmClient, console: Console, end: float, stream: StateStream | None = None
) -> Exit:
    """`monitor --json`: a JSON object per refresh, one a line (JSON Lines)."""
    start = time.monotonic()
    try:
        for now, rates in _refreshes(client, end, stream, MONITOR_REFRESH_S):
            line = json.dumps(monitor_json(client, rates, now - start))
            console.out(line, highlight=False)
            console.file.flush()  # a reader on a pipe gets each line as it comes
    except KeyboardInterrupt:
        pass
    return Exit.OK


def read_diagnostics(client: ArmClient) -> None:
    """A monitor refresh's Monitor readings and status flags of every device found."""
    try:
        client.read_diagnostics()
    except DriverError:
        pass  # the table and JSON show the link's state; the readings keep their last
