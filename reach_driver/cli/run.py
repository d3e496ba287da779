"""`run`: a controller in the loop on the arm, its summary, metrics and recording."""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import signal
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console
from rich.markup import escape

from protocol.models import ALPHA5, ArmModel
from reach_driver.cli.arms import angles_problem, given_model, in_scope
from reach_driver.cli.connect import connect
from reach_driver.cli.exits import (
    Exit,
    UsageError,
    for_operator,
    left_in_for_operator,
    notes,
    say_interrupted,
)
from reach_driver.cli.live import RunView, chain
from reach_driver.cli.recorder import CliRecorder, check_record, kept_viewers
from reach_driver.cli.render import (
    as_typed,
    blocking_faults,
    jsonable,
    print_metrics,
    print_summary,
)
from reach_driver.cli.report import summary_dict
from reach_driver.control import ControlLoop, Pacing, control_period
from reach_driver.controllers import (
    ControllerModelError,
    available_controllers,
    controller_report,
    load_controller,
    registered_list,
)
from reach_driver.errors import ArmFaultError, DriverError, Interrupted, RealtimeRefusedError
from reach_driver.realtime import ThreadRole
from reach_driver.records import ControlSummary
from reach_driver.safety import LimitKind
from reach_driver.watchdog import watchdog_too_short

if TYPE_CHECKING:
    pass


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
    check_record(args)
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
            client.read_status(model.joints), notes() if args.json else console
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
                keep_into=kept_viewers(args),
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
                notes().print(f"[yellow]recording incomplete[/]: {escape(recorder.failed)}")
            say_interrupted(signum, left_in)
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
        say_interrupted(signum, left_in)
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
