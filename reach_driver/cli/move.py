"""`move`: joints (or the tool, `--xyz`) to a target in POSITION mode, watched to the end."""

from __future__ import annotations

import argparse
import signal
import threading
import time
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from protocol import Mode, PacketID
from protocol.models import ALPHA5, ArmModel
from reach_driver.cli.arms import JointValues, angles_problem, in_scope
from reach_driver.cli.connect import connect
from reach_driver.cli.exits import (
    Exit,
    UsageError,
    left_in_for_operator,
    say_interrupted,
)
from reach_driver.cli.live import MoveView
from reach_driver.cli.recorder import CliRecorder, kept_viewers
from reach_driver.cli.render import (
    blocking_faults,
)
from reach_driver.client import ArmClient
from reach_driver.drawing import drawing_for
from reach_driver.errors import ArmFaultError, DriverError, Interrupted
from reach_driver.kinematics import tool_position
from reach_driver.link import EventKind, LinkState
from reach_driver.safety import LimitKind

if TYPE_CHECKING:
    pass
from reach_driver.cli.monitor import StateStream, wait_streaming


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
    stream: StateStream | None = None
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
                        None, meta, viewer=viewer, keep_into=kept_viewers(args), model=model
                    )
                    stream = StateStream(client, recorder, target)
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
                        wait_streaming(0.05, stream, stop)
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
            say_interrupted(signum, left_in)
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
