"""The subcommands: each takes the parsed options and a console and returns an exit status."""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console
from rich.live import Live
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from protocol import Mode, PacketID
from protocol.models import ALPHA5, ArmModel
from reach_driver import ik
from reach_driver.cli.arms import JointValues, angles_problem, given_model, in_scope
from reach_driver.cli.connect import connect, safety_config
from reach_driver.cli.exits import Exit, UsageError, for_operator, left_in_for_operator
from reach_driver.cli.live import MoveView, RunView, chain
from reach_driver.cli.recorder import CliRecorder, output_path_problem
from reach_driver.cli.render import (
    Roles,
    as_typed,
    blocking_faults,
    controllers_lines,
    diagnostics_table,
    info_json,
    info_tables,
    jsonable,
    monitor_json,
    monitor_line,
    monitor_table,
    print_metrics,
    print_recording,
    print_summary,
    workspace_json,
    workspace_point_line,
    workspace_tables,
)
from reach_driver.cli.report import summary_dict
from reach_driver.cli.tables import fitted, show_table
from reach_driver.client import ArmClient
from reach_driver.control import ControlLoop, Pacing, control_period
from reach_driver.controllers import (
    ControllerModelError,
    available_controllers,
    controller_report,
    describe_controllers,
    load_controller,
    registered_list,
)
from reach_driver.drawing import drawing_for
from reach_driver.errors import ArmFaultError, DriverError, Interrupted, RealtimeRefusedError
from reach_driver.kinematics import tool_position
from reach_driver.link import EventKind, LinkState
from reach_driver.realtime import ThreadRole
from reach_driver.records import ControlSummary
from reach_driver.safety import LimitKind, SafetyGuard
from reach_driver.state import ArmState, joint_name
from reach_driver.watchdog import watchdog_too_short

if TYPE_CHECKING:
    from reach_driver.recording import RunRecorder


def cmd_info(args: argparse.Namespace, console: Console) -> Exit:
    client = connect(args, console)
    try:
        # info only polls (it never asks for a heartbeat), but over UDP the arm streams to
        # the last host that wrote to it: say so if another client had a stream running.
        streaming = _streams_elsewhere(client)
        if streaming:
            _notes().print(
                f"[yellow]warning[/]: {streaming}: another client may be driving this arm; "
                "the arm now streams to this info instead (it sends its heartbeat to the last "
                "host that wrote to it), and a run there stops by its watchdog, naming this. "
                "One UDP arm serves one commanding client"
            )
        # Where each joint is now, beside its limits: the start of any move or run.
        client.request_many(client.found_devices, [PacketID.POSITION], partial=True)
        client.read_diagnostics()  # Monitor readings and status, read_info's joints carry them
        joints = client.read_info()
        if args.json:
            console.print_json(json.dumps(info_json(args.port, joints, client.model)))
            return Exit.OK
        tables = info_tables(args.port, joints, client.model)
        for table in (*tables, diagnostics_table(args.port, joints)):
            show_table(console, table)
        return Exit.OK
    finally:
        client.close()


def _streams_elsewhere(client: ArmClient) -> str:
    """Over a link other hosts share: which devices were streaming a heartbeat set up by
    another client ("E (0x05), D (0x04) streamed a heartbeat at 50 Hz"), or ""."""
    if not client.transport.shared_by_other_hosts:
        return ""
    rates = client.request_many(client.found_devices, [PacketID.HEARTBEAT_FREQUENCY], partial=True)
    hz = {
        d: r[PacketID.HEARTBEAT_FREQUENCY].data[0]
        for d, r in rates.items()
        if PacketID.HEARTBEAT_FREQUENCY in r and r[PacketID.HEARTBEAT_FREQUENCY].data
    }
    on = [d for d, f in hz.items() if f]
    if not on:
        return ""
    names = ", ".join(joint_name(d) for d in on)
    return f"{names} streamed a heartbeat at {max(hz[d] for d in on)} Hz"


def _kept(args: argparse.Namespace) -> list[RunRecorder] | None:
    """With --viewer-keep: where a command's recorder leaves its live viewer serving for
    `main` to wait on once the command is done (None: close it with the command)."""
    if not getattr(args, "viewer_keep", False):
        return None
    kept: list[RunRecorder] = args.kept_viewers
    return kept


def _check_record(args: argparse.Namespace) -> None:
    """Before the port is opened: `--record` must name a file, never the arm's port."""
    if args.record:
        problem = output_path_problem("--record", args.record, args.port, devices=True)
        if problem:
            raise UsageError(f"{problem}; nothing was sent")


def cmd_monitor(args: argparse.Namespace, console: Console) -> Exit:
    _check_record(args)
    client = connect(args, console)
    viewer = getattr(args, "viewer", None)
    recorder: CliRecorder | None = None
    stream: _StateStream | None = None
    try:
        devices = client.found_devices
        ids = (PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT, PacketID.MODE)
        rate = client.stream(ids, args.rate, devices)
        if rate != args.rate:
            _notes().print(
                f"[yellow]--rate {args.rate} Hz is more than the line carries for "
                f"{len(ids)} values of {len(devices)} devices: streaming at {rate} Hz[/yellow]"
            )
        _read_diagnostics(client)  # the first table (and a recording) starts with them
        if viewer is not None or args.record:
            meta = {"command": "monitor", "port": args.port, "rate_hz": rate}
            recorder = CliRecorder(
                args.record,
                meta,
                viewer=viewer,
                diagnostics=lambda: client.state.joints,
                keep_into=_kept(args),
                model=client.model,
            )
            stream = _StateStream(client, recorder)
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
    client: ArmClient, end: float, stream: _StateStream | None, every_s: float
) -> Iterator[tuple[float, dict[tuple[int, int], float]]]:
    """Every `every_s` until `end` (wall clock): the time, and each (device, packet id)'s
    update rate (Hz) since the refresh before; the Monitor readings are read afresh each time."""
    last_counts = client.table.count_snapshot()
    last_t = time.monotonic()
    while time.monotonic() < end:
        _wait(min(every_s, max(0.0, end - time.monotonic())), stream)
        now = time.monotonic()
        counts = client.table.count_snapshot()
        rates = {k: (n - last_counts.get(k, 0)) / (now - last_t) for k, n in counts.items()}
        last_counts, last_t = counts, now
        _read_diagnostics(client)
        yield now, rates


def _monitor_lines(
    client: ArmClient, console: Console, port: str, end: float, stream: _StateStream | None
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


class _StateStream:
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


def _wait(seconds: float, stream: _StateStream | None, stop: threading.Event | None = None) -> None:
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
    client: ArmClient, console: Console, end: float, stream: _StateStream | None = None
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


def _read_diagnostics(client: ArmClient) -> None:
    """A monitor refresh's Monitor readings and status flags of every device found."""
    try:
        client.read_diagnostics()
    except DriverError:
        pass  # the table and JSON show the link's state; the readings keep their last


def _notes() -> Console:
    return Console(stderr=True, highlight=False)


def cmd_move(args: argparse.Namespace, console: Console) -> Exit:
    scope = in_scope(args)
    try:
        wanted = JointValues.parse(args.angles)
    except ValueError as exc:
        raise UsageError(f"move: {exc}") from None
    if args.xyz is not None and args.angles:
        raise UsageError("move takes joint angles or --xyz X Y Z, not both")
    if args.xyz is None:
        problem = wanted.names_problem(scope) or (
            None if wanted.named else angles_problem("move", len(wanted.values), scope, jaw=True)
        )
        if problem:
            raise UsageError(f"{problem}; or --xyz X Y Z (mm) for a tool position")
    client = connect(args, console)
    try:
        target, jaw = _move_target(args, wanted, client)
    except BaseException:
        client.close()
        raise
    model = client.model
    devices = [*model.joints, model.jaw] if jaw is not None else list(model.joints)
    commanded = False
    recorder: CliRecorder | None = None
    stream: _StateStream | None = None
    viewer = getattr(args, "viewer", None)
    stop = threading.Event()  # set by a signal: the move ends at its next poll
    short: BaseException | None = None  # what ended the move short of its target
    lost = False
    try:
        try:
            with args.signals.taken(stop.set):
                if args.xyz is not None:  # joint targets by the driver's IK; out of reach: exit 3
                    target = client.solve_xyz(*args.xyz)
                # Check everything first: a refused target must leave every joint where it is.
                for dev, value in zip(model.joints, target, strict=True):
                    client.guard.check(dev, LimitKind.POSITION, float(value))
                if jaw is not None:
                    client.guard.check(model.jaw, LimitKind.POSITION, jaw)
                faults = blocking_faults(client.read_status(), console)
                if faults:
                    raise ArmFaultError(f"arm reports faults, not moving: {faults}")
                ids: tuple[PacketID, ...] = (PacketID.POSITION,)
                if viewer is not None:
                    ids = (PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT)
                    meta = {"command": "move", "port": args.port, "target": target.tolist()}
                    recorder = CliRecorder(
                        None, meta, viewer=viewer, keep_into=_kept(args), model=model
                    )
                    stream = _StateStream(client, recorder, target)
                client.stream(ids, 20, devices)
                q0 = client.read_joints((PacketID.POSITION,)).q
                if stop.is_set():
                    raise Interrupted(args.signals.first or signal.SIGINT)  # nothing commanded
                commanded = True
                client.set_mode(devices, Mode.POSITION)
                client.command_positions(target)
                if jaw is not None:
                    client.command_jaw(jaw)
                start_err = float(np.max(np.abs(target - q0))) or 1.0
                move_started = client.clock()
                deadline = time.monotonic() + args.move_timeout
                notes = Console(stderr=True, highlight=False)
                lines = MoveView(notes, enabled=not args.quiet, letters=model.joint_letters)
                with Progress(
                    TextColumn("[bold]move[/]"),
                    BarColumn(),
                    TextColumn("{task.fields[detail]}"),
                    TimeElapsedColumn(),
                    console=notes,
                    transient=True,
                    disable=args.quiet or not notes.is_terminal,
                ) as progress:
                    task = progress.add_task("move", total=1.0, detail="")
                    while True:
                        state = client.state
                        err = target - state.q
                        jaw_err = abs(jaw - state.jaw_mm) if jaw is not None else 0.0
                        worst = float(np.max(np.abs(err)))
                        detail = " ".join(
                            f"{j} {e:+.3f}" for j, e in zip(model.joint_letters, err, strict=True)
                        )
                        if jaw is not None:
                            detail += f" jaw {jaw - state.jaw_mm:+.2f} mm"
                        progress.update(
                            task,
                            completed=min(1.0, max(0.0, 1.0 - worst / start_err)),
                            detail=detail,
                        )
                        jaw_left = jaw - state.jaw_mm if jaw is not None else None
                        tool_err = _tool_error_mm(args, state.q, model)
                        done = (
                            worst <= args.tolerance
                            and jaw_err <= args.jaw_tolerance
                            and tool_err <= args.xyz_tolerance
                        )
                        lines.update(err, jaw_left, force=done)
                        if done:
                            progress.update(task, completed=1.0)
                            break
                        if stop.is_set():
                            break
                        if client.link_state is not LinkState.UP:
                            progress.stop()
                            _report_link_lost(client, target, move_started)
                            lost = True
                            break
                        faults = blocking_faults(state.faults, None)
                        if faults:
                            short = ArmFaultError(f"fault during the move: {faults}")
                            break
                        if time.monotonic() > deadline:
                            short = DriverError(
                                f"move timed out after {args.move_timeout:g} s; errors (rad) "
                                f"{detail}"
                            )
                            break
                        _wait(0.05, stream, stop)
                    if stream is not None:
                        stream.last(state)  # the state that ended the move (reached or not)
                if done:
                    console.print(f"[green]reached[/] within {args.tolerance} rad: {detail}")
                    if args.xyz is not None:
                        goal = ", ".join(f"{v:.1f}" for v in args.xyz)
                        console.print(f"tool centre point {tool_err:.2f} mm from ({goal}) mm")
                    return Exit.OK
        except BaseException as exc:  # a viewer, a bug, a KeyboardInterrupt not from a signal
            if not commanded:
                raise
            short = exc
        # Short of the target after commanding it: in position mode the joints would go on
        # there, so stop them as a run does, and say truthfully whether the arm confirmed it.
        left_in = left_in_for_operator(client.make_safe(devices).describe(), args.port)
        signum = args.signals.first
        if isinstance(short, Interrupted):
            short.left_in = left_in
            raise short
        if isinstance(short, KeyboardInterrupt):
            raise Interrupted(signal.SIGINT, left_in=left_in) from short
        console.print(f"arm left in {escape(left_in)}", soft_wrap=True)
        if signum is not None:
            _say_interrupted(signum, left_in)
            return Exit.for_signal(signum)
        if lost:
            return Exit.LINK_LOST
        assert short is not None
        raise short
    finally:
        if recorder is not None:
            recorder.close()
        try:
            client.stop_stream()
        except DriverError:
            pass
        client.close()


def _move_target(
    args: argparse.Namespace, wanted: JointValues, client: ArmClient
) -> tuple[np.ndarray, float | None]:
    """The joint target (the model's order; NaN until --xyz is solved) and the jaw's (mm or
    None) that `move` was given, checked against the arm that answered (UsageError, nothing
    sent but requests); joints not named keep their present angle."""
    model = client.model
    on = f"the {model.title} on {args.port}"
    jaw: float | None = args.jaw
    if args.xyz is not None:
        return np.full(model.n_joints, np.nan), jaw
    problem = wanted.names_problem((model,), on) or (
        None
        if wanted.named
        else angles_problem("move", len(wanted.values), (model,), jaw=True, on=on)
    )
    if problem:
        raise UsageError(f"{problem}; nothing was sent")
    if wanted.gives_jaw(model) and jaw is not None:
        raise UsageError("the jaw is given twice (with the angles and --jaw); nothing was sent")
    present = np.full(model.n_joints, np.nan)
    if wanted.named:
        present = client.read_joints((PacketID.POSITION,)).q
    return wanted.target(model, present, jaw)


def _tool_error_mm(args: argparse.Namespace, q: np.ndarray, model: ArmModel) -> float:
    """With --xyz: the distance (mm) of the reported angles' tool centre point from the
    target; 0 without."""
    if args.xyz is None:
        return 0.0
    point = tool_position(q) if model is ALPHA5 else drawing_for(model).tool_position(q)
    return float(np.linalg.norm(point * 1000.0 - np.asarray(args.xyz, dtype=float)))


def _report_link_lost(client: ArmClient, target: np.ndarray, move_started: float) -> None:
    """Why a move ended on a lost link: since when, and the last positions the arm sent."""
    now = client.clock()
    downs = [e.t for e in client.events if e.kind is EventKind.LINK_DOWN]
    since = downs[-1] if downs else now
    wall = time.time() - (now - since)
    stamp = time.strftime("%H:%M:%S", time.localtime(wall)) + f".{int(wall * 1e3) % 1000:03d}"
    state = client.state
    positions = []
    ages = []
    for letter, dev in zip(client.model.joint_letters, client.model.joints, strict=True):
        reading = state.joint(dev).position
        if reading is None:
            positions.append(f"{letter} -")
        else:
            positions.append(f"{letter} {reading.value:.4f}")
            ages.append(reading.age(now))
    age = f" ({max(ages):.2f} s old)" if ages else ""
    goal = " ".join(f"{v:.4f}" for v in target)
    message = (
        f"during the move: {client.link_reason}; down for {now - since:.2f} s "
        f"(since {stamp}, {since - move_started:.2f} s into the move); last known positions "
        f"(rad) {' '.join(positions)}{age}. The arm was commanded to {goal} in position mode "
        "and may still be moving there."
    )
    Console(stderr=True, highlight=False).print(
        f"[red]link lost[/] {escape(message)}", soft_wrap=True
    )


def cmd_run(args: argparse.Namespace, console: Console) -> Exit:
    params = dict(args.param)
    if args.controller not in available_controllers():  # a typo is a bad command line (2)
        raise UsageError(f"unknown controller {args.controller!r}; registered: {registered_list()}")
    if "arm" in params:
        raise UsageError("--param arm: the arm's model is --arm (or found at connect)")
    problem = angles_problem("run --target", len(args.target), in_scope(args))
    if problem:
        raise UsageError(problem)
    assumed = given_model(args) or ALPHA5
    controller = _run_controller(args, params, assumed)
    period, mismatch = control_period(controller, args.period)
    if args.pacing == Pacing.STREAM.value and not 1 <= round(1.0 / period) <= 255:
        raise UsageError(
            f"period {period:g} s needs a {1.0 / period:.3g} Hz heartbeat; with --pacing stream "
            "the period must be 1/255 s (3.9 ms) .. 1 s (--pacing poll allows down to 0.001 s)"
        )
    # Before the arm is touched: a period the watchdog cannot span trips on the first command.
    paced = 1.0 / round(1.0 / period) if args.pacing == Pacing.STREAM.value else period
    too_short = watchdog_too_short(paced, args.watchdog)
    if too_short is not None:
        given = "--period" if args.period else f"controller {args.controller!r}'s own period"
        raise UsageError(f"{given}: {too_short}")
    _check_record(args)
    if mismatch:
        Console(stderr=True, highlight=False).print(f"[yellow]warning[/]: {escape(mismatch)}")
    recorder: CliRecorder | None = None
    client = connect(args, console)
    summary: ControlSummary | None = None
    error: str | None = None
    try:
        model = client.model
        problem = angles_problem(
            "run --target", len(args.target), (model,), on=f"the {model.title} on {args.port}"
        )
        if problem:
            raise UsageError(f"{problem}; nothing was sent")
        if model is not assumed:  # found at connect: the controller for this arm
            controller = _run_controller(args, params, model)
            if control_period(controller, args.period)[0] != period:
                raise UsageError(
                    f"controller {args.controller!r} asks for another period on the "
                    f"{model.title}: give --period; nothing was sent"
                )
        target = np.array(args.target, dtype=float)
        for dev, value in zip(model.joints, target, strict=True):
            client.guard.check(dev, LimitKind.POSITION, float(value))
        # --realtime require: refused now, before a recording or viewer is opened, when the
        # reader was refused (the loop's thread asks as the loop starts, and is refused alike)
        refusal = client.realtime.report(ThreadRole.READER).refusal()
        if refusal is not None:
            raise RealtimeRefusedError(refusal)
        faults = blocking_faults(
            client.read_status(model.joints), _notes() if args.json else console
        )
        if faults:
            raise ArmFaultError(f"arm reports faults, not starting: {faults}")
        viewer = getattr(args, "viewer", None)
        if args.record or viewer is not None:
            meta: dict[str, object] = {
                "controller": args.controller,
                "params": params,
                "port": args.port,
                "period_s": period,
                "pacing": args.pacing,
                "target": target.tolist(),
                "seconds": args.seconds,
            }
            recorder = CliRecorder(
                args.record,
                meta,
                viewer=viewer,
                diagnostics=lambda: client.state.joints,
                keep_into=_kept(args),
                model=model,
            )
            client.read_diagnostics()  # the run's recording opens with every device's readings
        view = RunView(
            Console(stderr=True, highlight=False),
            args.seconds,
            enabled=not args.quiet,
            letters=model.joint_letters,
        )
        hook = chain(recorder.on_step if recorder is not None else None, view.on_step)
        loop = ControlLoop(client, controller, period, pacing=args.pacing, on_step=hook)
        # Everything loaded so far (modules, the controller, rerun) lives as long as the run: a
        # full collection during it would scan all of it with every thread stopped (34 ms on
        # a busy 2-core host); frozen, the collector sees only what the run allocates.
        gc.collect()
        gc.freeze()
        signum: int | None = None
        with args.signals.taken(loop.stop):  # a signal ends the loop like any other end
            try:
                with view:
                    summary = loop.run(target, args.seconds)
            except Interrupted as exc:  # a KeyboardInterrupt not from our handler
                if exc.summary is None:
                    raise
                summary, signum = exc.summary, exc.signum
        signum = args.signals.first or signum
        if signum is not None and summary.error is None and summary.stopped_by != "duration":
            why = (
                f"interrupted by {signal.Signals(signum).name} at t = {summary.loop_seconds:.2f} s"
            )
            summary = dataclasses.replace(summary, error=why, stopped_by=why)
        error = summary.error
        report = controller_report(controller)
        if recorder is not None:
            try:
                client.read_diagnostics()  # how the devices ended the run, for the recording
            except DriverError:
                pass  # a lost link is the summary's to report; the readings keep their last
            # before the last lines, which say how it went
            recorder.finish(summary, error, report)
        left_in = left_in_for_operator(summary.left_in, args.port)
        if signum is not None:
            code = Exit.for_signal(signum)
        elif summary.error:
            code = Exit.FAILED
        elif recorder is not None and recorder.failed:
            code = Exit.RECORDING_INCOMPLETE
        else:
            code = Exit.OK
        if args.json:
            out = summary_dict(summary)
            out.update(
                exit=int(code),
                arm=model.name,
                controller=args.controller,
                controller_report=report,
                target=summary.target,
                error=None if summary.error is None else for_operator(summary.error),
                left_in=left_in,
                record=args.record,
                recording_failed=recorder.failed if recorder is not None else None,
            )
            console.out(json.dumps(jsonable(out)), highlight=False)
            if recorder is not None and recorder.failed:
                _notes().print(f"[yellow]recording incomplete[/]: {escape(recorder.failed)}")
            _say_interrupted(signum, left_in)
            return code
        print_summary(console, summary)
        print_metrics(console, summary)
        if report:
            said = report.get("summary")
            text = said if isinstance(said, str) else json.dumps(jsonable(report))
            console.print(f"controller {escape(args.controller)}: {escape(text)}", soft_wrap=True)
        console.print(f"arm left in {escape(left_in)}", soft_wrap=True)
        if recorder is not None and recorder.failed:
            console.print(
                f"[yellow]recording incomplete[/]: {escape(recorder.failed)}; what reached "
                f"the file before that reads back with `{escape(as_typed('reach-driver'))} inspect "
                f"{escape(args.record)}`",
                soft_wrap=True,
            )
        elif args.record:
            record = escape(args.record)
            console.print(
                f"recorded {record}: open it with `{escape(as_typed('rerun'))} {record}`, "
                f"summarise it with `{escape(as_typed('reach-driver'))} inspect {record}`",
                soft_wrap=True,  # keep the commands copyable
            )
        if summary.error:
            console.print(f"[red]run failed[/]: {escape(for_operator(summary.error))}")
        _say_interrupted(signum, left_in)
        return code
    finally:
        if recorder is not None:
            recorder.finish(summary, error)  # a no-op once finished
        client.close()


def _run_controller(args: argparse.Namespace, params: dict[str, Any], model: ArmModel) -> Any:
    """`run`'s controller for an arm of `model`, or the one line (UsageError) why not."""
    try:
        return load_controller(args.controller, arm=model, **params)
    except ControllerModelError as exc:
        raise UsageError(f"{exc}; nothing was sent") from None
    except (OSError, ValueError) as exc:  # a missing weights file, a bad gain...
        given = " ".join(f"{k}={v}" for k, v in params.items())
        raise UsageError(f"controller {args.controller!r} with --param {given}: {exc}") from None


def _say_interrupted(signum: int | None, left_in: str) -> None:
    """The last line on stderr of a move or run a signal ended."""
    if signum is not None:
        _notes().print(
            f"interrupted: by {signal.Signals(signum).name}; arm left in {escape(left_in)}",
            soft_wrap=True,
        )


def cmd_controllers(args: argparse.Namespace, console: Console) -> Exit:
    infos = describe_controllers()
    if args.json:
        console.print_json(json.dumps([info.to_dict() for info in infos], default=str))
        return Exit.OK
    for line in controllers_lines(infos):
        console.print(line, markup=False, highlight=False, soft_wrap=True)
    return Exit.OK


def cmd_workspace(args: argparse.Namespace, console: Console) -> Exit:
    """Where the tool reaches inside the limits `move --xyz` would use on an arm of the model
    (`--arm`, the Alpha 5 by default) reporting the factory ones (the same guard, the same
    solver); opens no port."""
    model = given_model(args) or ALPHA5
    try:
        drawing = drawing_for(model)
    except ValueError as exc:
        raise UsageError(f"workspace: {exc}") from None
    roles = Roles.of(model, drawing)
    margin = float(args.position_margin)
    limits = np.array(SafetyGuard(safety_config(args), model).position_limits())
    env = ik.envelope(limits, drawing)
    sol = None
    if args.xyz is not None:
        middle = limits.mean(axis=1)  # no arm, no present angles: start mid-range
        sol = ik.nearest_on(drawing, args.xyz, middle, limits)
    if args.json:
        console.print_json(json.dumps(workspace_json(env, margin, args.xyz, sol, roles)))
    else:
        for table in workspace_tables(env, margin, roles):
            show_table(console, table)
        if sol is not None:
            console.print(escape(workspace_point_line(args.xyz, sol, roles)), soft_wrap=True)
    return Exit.OK if sol is None or sol.reachable else Exit.LIMIT


def cmd_inspect(args: argparse.Namespace, console: Console) -> Exit:
    from reach_driver.rrd_summary import RecordingReadError, summarize_recording

    try:
        summary: dict[str, Any] = summarize_recording(args.file)
    except (RecordingReadError, OSError) as exc:
        console.print(
            f"[red]error[/]: cannot read {escape(args.file)}: {escape(str(exc))}", soft_wrap=True
        )
        return Exit.FAILED
    if args.json:  # strict JSON: NaN and infinities are null
        console.print_json(json.dumps(jsonable(summary), allow_nan=False))
        return Exit.OK
    print_recording(console, summary)
    return Exit.OK


def cmd_export(args: argparse.Namespace, console: Console) -> Exit:
    from reach_driver.export import ExportError, export_recording
    from reach_driver.rrd_summary import RecordingReadError

    problem = output_path_problem("--to", args.to, None, devices=True)
    if problem:
        raise UsageError(problem)
    try:
        report = export_recording(args.file, args.to)
    except RecordingReadError as exc:  # as inspect: the file, not the command line, is wrong
        _notes().print(
            f"[red]error[/]: cannot export {escape(args.file)}: {escape(str(exc))}", soft_wrap=True
        )
        return Exit.FAILED
    except ExportError as exc:
        raise UsageError(f"cannot export {args.file}: {exc}") from None
    except OSError as exc:
        raise DriverError(f"cannot write {args.to}: {exc}; nothing was written") from None
    what = f"{report.steps} steps"
    if report.events:
        what += f", {report.events} events"
    console.print(f"wrote {escape(str(report.out))}: {what}", soft_wrap=True)
    if report.truncated_bytes or not report.closed_cleanly:
        cut = f" ({report.truncated_bytes} bytes of a cut message skipped)"
        _notes().print(
            f"note: {escape(args.file)} was not closed by its writer: exported what it "
            f"holds{cut if report.truncated_bytes else ''}",
            soft_wrap=True,
        )
    return Exit.OK


COMMANDS: dict[str, Callable[[argparse.Namespace, Console], Exit]] = {
    "info": cmd_info,
    "monitor": cmd_monitor,
    "move": cmd_move,
    "run": cmd_run,
    "controllers": cmd_controllers,
    "inspect": cmd_inspect,
    "export": cmd_export,
    "workspace": cmd_workspace,
}
