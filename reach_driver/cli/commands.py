"""The subcommands: each takes the parsed options and a console and returns an exit status."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console
from rich.markup import escape

from protocol import PacketID
from protocol.models import ALPHA5
from reach_driver import ik
from reach_driver.cli.arms import given_model
from reach_driver.cli.connect import connect, safety_config
from reach_driver.cli.exits import (
    Exit,
    UsageError,
    notes,
)
from reach_driver.cli.recorder import output_path_problem
from reach_driver.cli.render import (
    Roles,
    controllers_lines,
    diagnostics_table,
    info_json,
    info_tables,
    jsonable,
    print_recording,
    workspace_json,
    workspace_point_line,
    workspace_tables,
)
from reach_driver.cli.tables import show_table
from reach_driver.client import ArmClient
from reach_driver.controllers import (
    describe_controllers,
)
from reach_driver.drawing import drawing_for
from reach_driver.errors import DriverError
from reach_driver.safety import SafetyGuard
from reach_driver.state import joint_name

if TYPE_CHECKING:
    pass
from reach_driver.cli.monitor import cmd_monitor
from reach_driver.cli.move import cmd_move
from reach_driver.cli.run import cmd_run


def cmd_info(args: argparse.Namespace, console: Console) -> Exit:
    client = connect(args, console)
    try:
        # info only polls (it never asks for a heartbeat), but over UDP the arm streams to
        # the last host that wrote to it: say so if another client had a stream running.
        streaming = _streams_elsewhere(client)
        if streaming:
            notes().print(
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
        notes().print(
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
        notes().print(
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
