"""`reach-driver`: talk to a Reach Alpha 5 (or the virtual arm) from the command line."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from enum import IntEnum
from types import FrameType
from typing import Any

import numpy as np
from rich.console import Console
from rich.live import Live
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from protocol import DeviceID, Mode, PacketID
from protocol.alpha5 import JAW, JOINT_LETTERS, JOINTS, TORQUE_PER_AMP_NM
from reach_driver.client import ArmClient
from reach_driver.control import (
    ControlLoop,
    ControlSummary,
    LoopTrace,
    Pacing,
    StepRecord,
    control_period,
)
from reach_driver.controllers import available_controllers, load_controller
from reach_driver.errors import (
    ArmFaultError,
    BadUrlError,
    DriverError,
    GarbageError,
    LimitError,
    LinkDownError,
    NoResponseError,
    PortNotFoundError,
    PortPermissionError,
    TransportError,
)
from reach_driver.interfaces import open_transport
from reach_driver.link import ClientEvent, EventKind
from reach_driver.metrics import METRIC_KEYS, Metrics, Trace, compute_metrics
from reach_driver.safety import LimitKind, SafetyConfig
from reach_driver.state import JointState, joint_name
from reach_driver.transport import DEFAULT_BAUD

LINK_FLAGS = frozenset({"SERIAL_ERROR", "CRC_ERROR"})

DESCRIPTION = """\
Talk to a Reach Alpha 5 arm, or the virtual arm (reach-sim), over the Reach/BPL serial
protocol.

--port takes a serial device (/dev/ttyUSB0), any pyserial URL (loop://, rfc2217://...),
udp://HOST[:PORT] for Ethernet arms (port 6789 by default) or can://INTERFACE/CHANNEL for
an arm behind a CAN gateway (see docs/can-tunnel.md). It defaults to $REACH_PORT.

Joint angles are the arm's own, in radians, in the order E D C B (base, shoulder, elbow,
wrist); the jaw is in mm. Safety is always on: commands outside the limits the arm reports
are refused before anything is sent, and Ctrl-C leaves the arm in a safe mode.
"""

EPILOG = """\
examples:
  reach-driver --port /dev/ttyUSB0 info
  reach-driver --port udp://192.168.2.3 monitor
  reach-driver --port /dev/ttyUSB0 move 3.1 1.5 1.5 3.0 --jaw 8
  reach-driver --port /dev/ttyUSB0 run --controller pid --target 3.1 1.5 1.5 3.0 --seconds 10
  reach-driver --port /dev/ttyUSB0 run --controller ddpg --target 5.78 1.97 1.67 3.96 \
      --seconds 20 --record run.rrd
  reach-driver inspect run.rrd

exit status: 0 done; 1 failed (timeout, fault, lost link); 2 bad usage; 3 refused by a
limit (nothing moved); 4 no arm (wrong port, no permission, nothing answering, wrong baud);
130 interrupted (arm left in a safe mode). docs/hil.md: using a real arm.
"""


class Exit(IntEnum):
    OK = 0
    FAILED = 1
    USAGE = 2
    LIMIT = 3
    NO_ARM = 4
    INTERRUPTED = 130


def _floats(text: str) -> float | list[float]:
    parts = [p for p in text.split(",") if p.strip()]
    values = [float(p) for p in parts]
    return values[0] if len(values) == 1 else values


def _param(text: str) -> tuple[str, Any]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, _floats(value)
    except ValueError:
        return key, value


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="reach-driver",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--port",
        default=os.environ.get("REACH_PORT"),
        help="device path, pyserial URL, udp://HOST[:PORT] or can://IF/CHANNEL "
        "(default: $REACH_PORT)",
    )
    parser.add_argument(
        "--baud", type=int, default=DEFAULT_BAUD, help="serial baud rate (default 115200, 8N1)"
    )
    parser.add_argument(
        "--rs485",
        action="store_true",
        help="half-duplex RS-485: space writes, never broadcast requests",
    )
    parser.add_argument(
        "--timeout",
        type=_positive,
        default=0.1,
        help="seconds to wait for each reply before retrying (default 0.1)",
    )
    parser.add_argument(
        "--retries", type=int, default=2, help="retries per request before giving up (default 2)"
    )
    parser.add_argument(
        "--watchdog",
        type=_positive,
        default=0.2,
        help="seconds without a command or fresh feedback before the arm is put in a safe "
        "mode during velocity/current control (default 0.2)",
    )
    parser.add_argument(
        "--max-current",
        metavar="MA[,MA,MA,MA]",
        help="tighten the current limits the arm reports: one value for every joint or four "
        "comma-separated (E,D,C,B), in mA; a controller's output is clipped to them (for "
        "first runs on a real arm)",
    )
    parser.add_argument(
        "--position-margin",
        type=float,
        default=0.0,
        metavar="RAD",
        help="keep this far inside the arm's position limits (default 0)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log link events in detail")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sub.add_parser(
        "info",
        help="devices found, versions, serials, limits, modes, status flags",
        description="List the devices that answer with their software versions, serial and "
        "model numbers, modes, limits and hardware status flags by name.",
    ).add_argument("--json", action="store_true", help="print JSON instead of a table")

    mon = sub.add_parser(
        "monitor",
        help="live table of joint states, update rates and link error counters",
        description="Stream positions, velocities, currents and modes and show them live "
        "with per-joint update rates and the link's error counters. Ctrl-C to stop.",
    )
    mon.add_argument("--rate", type=int, default=10, help="heartbeat rate in Hz (default 10)")
    mon.add_argument("--seconds", type=_positive, help="stop after this many seconds")

    move = sub.add_parser(
        "move",
        help="position-mode move of E D C B (rad) and optionally the jaw (mm)",
        description="Move the four joints to absolute angles (rad, as the arm reports them) "
        "in position mode and wait until every joint is within --tolerance. Targets outside "
        "the limits are refused before anything moves (exit 3).",
    )
    move.add_argument("angles", nargs=4, type=float, metavar=("E", "D", "C", "B"))
    move.add_argument("--jaw", type=float, metavar="MM", help="jaw opening in mm")
    move.add_argument(
        "--tolerance", type=_positive, default=0.02, help="rad per joint (default 0.02)"
    )
    move.add_argument("--jaw-tolerance", type=_positive, default=0.5, help="mm (default 0.5)")
    move.add_argument(
        "--timeout", dest="move_timeout", type=_positive, default=60.0, help="s (default 60)"
    )

    run = sub.add_parser(
        "run",
        help="closed-loop control with a registered controller",
        description="Run a controller (found by name in the reach_stack.controllers entry "
        "points) in current mode towards a target, then leave the arm in a safe mode and "
        "print the final errors, timing statistics and the run's metrics (energy, RMSE, MIE, "
        "MSSE, overshoot, settling time, reached; docs/metrics.md) computed from the angles "
        "the arm reported, with torque = measured current x the joint's torque constant "
        f"(E/D/C {TORQUE_PER_AMP_NM[0]:.3g}, B {TORQUE_PER_AMP_NM[3]:.3g} N m/A). "
        "With --pacing stream (default) the arm's heartbeat paces "
        "the loop and time is arm time: against reach-sim --speed X a run takes 1/X of the "
        "wall time and gives the same metrics.",
        epilog="exit status: 0 the run completed (whether or not it reached the target: see "
        "'reached'); 1 it was cut short (lost link, watchdog, fault, controller error); 3 the "
        "target is outside a limit (nothing moved); 4 no arm; 130 interrupted.",
    )
    run.add_argument("--controller", required=True, help="e.g. pid, mpc, ddpg")
    run.add_argument("--target", nargs=4, type=float, required=True, metavar=("E", "D", "C", "B"))
    run.add_argument("--seconds", type=_positive, required=True, help="loop (arm) seconds")
    run.add_argument(
        "--period",
        type=_positive,
        help="control period in arm seconds (default: the controller's own, e.g. the rate a "
        "policy was trained at, else 0.05)",
    )
    run.add_argument(
        "--pacing",
        choices=[p.value for p in Pacing],
        default=Pacing.STREAM.value,
        help="stream: the arm's heartbeat paces the loop (arm time); poll: host clock",
    )
    run.add_argument(
        "--param",
        action="append",
        type=_param,
        default=[],
        metavar="KEY=VALUE",
        help="controller parameter (repeatable; comma-separated values give a list)",
    )
    run.add_argument("--record", metavar="FILE.rrd", help="record the run for Rerun")

    sub.add_parser("controllers", help="list the registered controllers")
    ins = sub.add_parser(
        "inspect",
        help="summarise a recorded run (.rrd): duration, final errors, events, metrics",
    )
    ins.add_argument("file", help="a recording written by `run --record`, or `reach-sim --record`")
    ins.add_argument("--json", action="store_true", help="print the summary as JSON")
    return parser


# ---------------------------------------------------------------------------------- helpers


def _connect(args: argparse.Namespace, console: Console) -> ArmClient:
    if not args.port:
        raise BadUrlError(
            "no port: give --port (device, pyserial URL or udp://HOST) or set $REACH_PORT"
        )
    safety = _safety(args)  # checked by main() already
    transport = open_transport(args.port, baud=args.baud, rs485=args.rs485)
    client = ArmClient(
        transport, safety=safety, request_timeout_s=args.timeout, retries=args.retries
    )

    # Events and warnings go to stderr so `info --json` stays parseable.
    notes = Console(stderr=True, highlight=False)

    def report(event: ClientEvent) -> None:
        style = "green" if event.kind in (EventKind.LINK_UP, EventKind.FAULT_CLEARED) else "red"
        notes.print(f"[{style}]{event.kind.value}[/]: {event.message}")

    client.on_event(report)
    client.start()
    for warning in client.warnings:
        notes.print(f"[yellow]warning[/]: {warning}")
    return client


def _safety(args: argparse.Namespace) -> SafetyConfig:
    currents: dict[int, float] = {}
    if args.max_current:
        try:
            given = [float(v) for v in args.max_current.split(",")]
        except ValueError:
            raise ValueError(f"--max-current takes mA values, got {args.max_current!r}") from None
        if len(given) not in (1, 4) or not all(math.isfinite(v) and v > 0 for v in given):
            raise ValueError(
                "--max-current takes one positive value or four comma-separated (E,D,C,B), "
                f"got {args.max_current!r}"
            )
        values = given * 4 if len(given) == 1 else given
        currents = {int(d): v for d, v in zip(JOINTS, values, strict=True)}
    if not (math.isfinite(args.position_margin) and args.position_margin >= 0):
        raise ValueError(f"--position-margin must be >= 0 rad, got {args.position_margin}")
    return SafetyConfig(
        watchdog_s=args.watchdog,
        current_limits_mA=currents,
        position_margin=args.position_margin,
    )


def _fmt(value: float | None, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def _range(js: JointState, kind: LimitKind) -> str:
    reading = getattr(js, f"{kind.value}_limits")
    if reading is None:
        return "-"
    lo, hi = reading.value
    return f"{lo:.4g} .. {hi:.4g}"


def _mode(js: JointState) -> str:
    if js.mode is None:
        return "-"
    value = js.mode.value
    return value.name.lower() if isinstance(value, Mode) else f"0x{value:02X}"


# ---------------------------------------------------------------------------------- commands


def cmd_info(args: argparse.Namespace, console: Console) -> Exit:
    client = _connect(args, console)
    try:
        # Where each joint is now, beside its limits: the start of any move or run.
        client.request_many(client.found_devices, [PacketID.POSITION], partial=True)
        joints = client.read_info()
        if args.json:
            out = {}
            for dev, js in joints.items():
                out[DeviceID(dev).name] = {
                    "device": dev,
                    "mode": _mode(js),
                    "software_version": js.software_version.value if js.software_version else None,
                    "serial_number": js.serial_number.value if js.serial_number else None,
                    "model_number": js.model_number.value if js.model_number else None,
                    "position": js.position.value if js.position else None,
                    "limits": {
                        kind.value: list(getattr(js, f"{kind.value}_limits").value)
                        for kind in LimitKind
                        if getattr(js, f"{kind.value}_limits") is not None
                    },
                    "status_flags": js.fault_names,
                }
            console.print_json(json.dumps({"port": args.port, "devices": out}))
            return Exit.OK
        table = Table(title=f"Reach arm on {args.port}: {len(joints)} device(s)")
        for column in (
            "device",
            "mode",
            "version",
            "serial",
            "model",
            "position",
            "position limits",
            "velocity limits",
            "current limits (mA)",
            "status",
        ):
            table.add_column(column)
        for dev, js in joints.items():
            status = js.fault_names
            table.add_row(
                joint_name(dev),
                _mode(js),
                js.software_version.value if js.software_version else "-",
                _fmt(js.serial_number.value, 0) if js.serial_number else "-",
                _fmt(js.model_number.value, 0) if js.model_number else "-",
                _fmt(js.position.value) if js.position else "-",
                _range(js, LimitKind.POSITION),
                _range(js, LimitKind.VELOCITY),
                _range(js, LimitKind.CURRENT),
                ("[red]" + ", ".join(status) + "[/]")
                if status
                else ("ok" if js.status is not None else "-"),
            )
        console.print(table)
        return Exit.OK
    finally:
        client.close()


def _monitor_table(client: ArmClient, rates: dict[tuple[int, int], float], port: str) -> Table:
    now = client.clock()
    state = client.state
    table = Table(title=f"{port}: link {client.link_state.value}")
    for column in ("joint", "mode", "position", "velocity", "current mA", "age ms", "rate Hz"):
        table.add_column(column, justify="right")
    for dev in (*JOINTS, JAW):
        js = state.joint(dev)
        age = js.position.age(now) * 1e3 if js.position else math.nan
        table.add_row(
            joint_name(dev),
            _mode(js),
            _fmt(js.position.value if js.position else None),
            _fmt(js.velocity.value if js.velocity else None),
            _fmt(js.current.value if js.current else None, 1),
            _fmt(age, 0),
            _fmt(rates.get((int(dev), int(PacketID.POSITION)), math.nan), 1),
        )
    ts, ds, cs = client.transport.stats, client.decoder_stats, client.stats
    bad = ", ".join(f"{r.value} {n}" for r, n in ds.bad_frames.items() if n) or "none"
    table.caption = (
        f"bytes in {ts.bytes_in} out {ts.bytes_out} | frames ok {ds.good_frames} "
        f"bad {ds.bad_total} ({bad}) | discarded bytes {ds.bytes_discarded} | foreign datagrams "
        f"{ts.foreign_datagrams} | lost CAN frames {ts.lost_can_frames} | reconnects "
        f"{cs.reconnects} | request timeouts {cs.request_timeouts}"
    )
    return table


def cmd_monitor(args: argparse.Namespace, console: Console) -> Exit:
    client = _connect(args, console)
    try:
        devices = client.found_devices
        ids = (PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT, PacketID.MODE)
        client.stream(ids, args.rate, devices)
        end = time.monotonic() + args.seconds if args.seconds else math.inf
        last_counts = client.table.count_snapshot()
        last_t = time.monotonic()
        rates: dict[tuple[int, int], float] = {}
        with Live(
            _monitor_table(client, rates, args.port),
            console=console,
            refresh_per_second=4,
            transient=False,
            auto_refresh=False,
        ) as live:
            while time.monotonic() < end:
                time.sleep(min(0.5, max(0.0, end - time.monotonic())))
                now = time.monotonic()
                counts = client.table.count_snapshot()
                rates = {k: (n - last_counts.get(k, 0)) / (now - last_t) for k, n in counts.items()}
                last_counts, last_t = counts, now
                live.update(_monitor_table(client, rates, args.port), refresh=True)
        return Exit.OK
    finally:
        client.close()


def _blocking_faults(flags: dict[int, list[str]], console: Console | None) -> str:
    """Status flags that must stop a move, as text ('' if none). Link error flags (a CRC or
    serial error the arm saw on the line) are only reported: they say nothing about the
    motors, and the arm clears them by itself."""
    blocking = []
    for dev, names in flags.items():
        link = [n for n in names if n in LINK_FLAGS]
        other = [n for n in names if n not in LINK_FLAGS]
        if link and console is not None:
            console.print(f"[yellow]warning[/]: {joint_name(dev)} reports {', '.join(link)}")
        if other:
            blocking.append(f"{joint_name(dev)}: {', '.join(other)}")
    return "; ".join(blocking)


def cmd_move(args: argparse.Namespace, console: Console) -> Exit:
    target = np.array(args.angles, dtype=float)
    client = _connect(args, console)
    try:
        # Check everything first: a refused target must leave every joint where it is.
        for dev, value in zip(JOINTS, target, strict=True):
            client.guard.check(dev, LimitKind.POSITION, float(value))
        if args.jaw is not None:
            client.guard.check(JAW, LimitKind.POSITION, args.jaw)
        faults = _blocking_faults(client.read_status(), console)
        if faults:
            raise ArmFaultError(f"arm reports faults, not moving: {faults}")
        devices = [*JOINTS, JAW] if args.jaw is not None else list(JOINTS)
        client.stream((PacketID.POSITION,), 20, devices)
        q0 = client.read_joints((PacketID.POSITION,)).q
        client.set_mode(devices, Mode.POSITION)
        client.command_positions(target)
        if args.jaw is not None:
            client.command_jaw(args.jaw)
        start_err = float(np.max(np.abs(target - q0))) or 1.0
        deadline = time.monotonic() + args.move_timeout
        with Progress(
            TextColumn("[bold]move[/]"),
            BarColumn(),
            TextColumn("{task.fields[detail]}"),
            TimeElapsedColumn(),
            console=console,
            transient=False,
        ) as progress:
            task = progress.add_task("move", total=1.0, detail="")
            while True:
                state = client.state
                err = target - state.q
                jaw_err = abs(args.jaw - state.jaw_mm) if args.jaw is not None else 0.0
                worst = float(np.max(np.abs(err)))
                detail = " ".join(f"{j} {e:+.3f}" for j, e in zip(JOINT_LETTERS, err, strict=True))
                if args.jaw is not None:
                    detail += f" jaw {args.jaw - state.jaw_mm:+.2f} mm"
                progress.update(
                    task, completed=min(1.0, max(0.0, 1.0 - worst / start_err)), detail=detail
                )
                if worst <= args.tolerance and jaw_err <= args.jaw_tolerance:
                    progress.update(task, completed=1.0)
                    break
                faults = _blocking_faults(state.faults, None)
                if faults:
                    client.safe_stop(devices)
                    raise ArmFaultError(f"fault during the move, joints stopped: {faults}")
                if time.monotonic() > deadline:
                    raise DriverError(
                        f"move timed out after {args.move_timeout:g} s; errors (rad) {detail}"
                    )
                time.sleep(0.05)
        console.print(f"[green]reached[/] within {args.tolerance} rad: {detail}")
        return Exit.OK
    finally:
        try:
            client.stop_stream()
        except DriverError:
            pass
        client.close()


def _recorder_hook(
    path: str, meta: dict[str, object]
) -> tuple[Callable[[StepRecord], None], Callable[[ControlSummary | None, str | None], None]]:
    """Wire `--record` to reach_driver.recording; fails before anything moves if unavailable."""
    try:
        from reach_driver import recording
    except ImportError as exc:
        raise DriverError(
            f"--record needs reach_driver.recording, which failed to import: {exc}"
        ) from None
    rec = recording.RunRecorder(path, metadata=meta)
    rec.log_event("start")

    def on_step(r: StepRecord) -> None:
        rec.log_step(
            recording.StepSample(
                t=r.t,
                step=r.step,
                q=r.q,
                qdot=r.qdot,
                target=r.target,
                current_cmd_mA=r.command_mA,
                current_meas_mA=r.current_mA,
                torque_Nm=r.torque_Nm,
            )
        )
        rec.log_link(r.t, r.step, r.good_frames, r.bad_frames, r.state_age_s)

    def finish(summary: ControlSummary | None, error: str | None) -> None:
        if summary is not None and summary.trace is not None and summary.steps:
            # The state that ended the run, so the recording scores like the printed metrics.
            tr = summary.trace
            rec.log_step(
                recording.StepSample(
                    t=float(tr.t[-1]),
                    step=summary.steps,
                    q=tr.q[-1],
                    qdot=tr.qdot[-1],
                    target=summary.target,
                    current_cmd_mA=np.zeros(4),
                    current_meas_mA=tr.current_mA[-1],
                    torque_Nm=tr.torque_Nm[-1],
                )
            )
        if error:
            rec.log_event(error, level="ERROR")
        if summary is not None:
            if summary.left_in:
                rec.log_event(f"arm left in {summary.left_in}")
            rec.log_summary(_summary_dict(summary))
        rec.log_event("stop")
        rec.close()

    return on_step, finish


def run_metrics(summary: ControlSummary) -> Metrics | None:
    """The run scored like an evaluation episode (on the angles the arm reported)."""
    tr = summary.trace
    if tr is None or tr.samples < 2:
        return None
    return compute_metrics(trace_for_metrics(tr, summary.target))


def trace_for_metrics(tr: LoopTrace, target: np.ndarray) -> Trace:
    return Trace(dt=tr.dt, q=tr.q, qdot=tr.qdot, tau=tr.torque_Nm, target=target)


def _summary_dict(s: ControlSummary) -> dict[str, object]:
    t = s.timing
    metrics = run_metrics(s)
    return {
        "ok": s.ok,
        "stopped_by": s.stopped_by,
        "steps": s.steps,
        "loop_seconds": s.loop_seconds,
        "wall_seconds": s.wall_seconds,
        "final_q": s.final_q.tolist(),
        "final_error": s.final_error.tolist(),
        "saturated_steps": s.saturated_steps,
        "barrier_steps": s.barrier_steps,
        "rate_hz": t.rate_hz,
        "arm_speed": t.arm_speed,
        "period_jitter_s": t.period_jitter_s,
        "state_age_p99_s": t.state_age_p99_s,
        "latency_p50_s": t.latency_p50_s,
        "latency_p99_s": t.latency_p99_s,
        "missed_deadlines": t.missed_deadlines,
        "skipped_states": t.skipped_states,
        "partial_states": t.partial_states,
        "incomplete_ticks": t.incomplete_ticks,
        "left_in": s.left_in,
        "metrics": None if metrics is None else metrics.as_dict(),
    }


METRIC_LABELS = {
    "energy_j": ("energy", "J"),
    "rmse": ("RMSE", "rad"),
    "mie": ("MIE", "rad s"),
    "msse": ("MSSE", "rad"),
    "overshoot_pct": ("overshoot", "%"),
    "settling_time_s": ("settling time", "s"),
    "reached": ("reached", ""),
}


def _print_metrics(console: Console, s: ControlSummary) -> None:
    metrics = run_metrics(s)
    if metrics is None:
        console.print("metrics: none (fewer than two states were seen)")
        return
    values = metrics.as_dict()
    table = Table(title="metrics (docs/metrics.md; from the reported angles)")
    for key in METRIC_KEYS:
        name, unit = METRIC_LABELS[key]
        table.add_column(f"{name} [{unit}]" if unit else name, justify="right")
    cells = []
    for key in METRIC_KEYS:
        value = values[key]
        cells.append(("yes" if value else "[red]no[/]") if isinstance(value, bool)
                     else f"{float(value):.4g}")
    table.add_row(*cells)
    console.print(table)
    tr = s.trace
    assert tr is not None
    measured = int(np.isfinite(tr.current_mA[1:]).all(axis=1).sum())
    kt = "/".join(f"{k:.3g}" for k in TORQUE_PER_AMP_NM)
    source = "commanded" if measured == 0 else "measured"
    note = f"torque = {source} current x {kt} N m/A (E D C B)"
    if 0 < measured < tr.samples - 1:
        note += f" (commanded on the {tr.samples - 1 - measured} samples without a reading)"
    if tr.filled:
        note += f"; {tr.filled} incomplete states interpolated"
    console.print(note)


def _print_summary(console: Console, s: ControlSummary) -> None:
    table = Table(title=f"run: {s.steps} steps, {s.loop_seconds:.2f} s loop time")
    for column in ("joint", "target", "final", "error"):
        table.add_column(column, justify="right")
    for j, tgt, q, e in zip(JOINT_LETTERS, s.target, s.final_q, s.final_error, strict=True):
        table.add_row(j, _fmt(tgt), _fmt(q), _fmt(e))
    console.print(table)
    t = s.timing
    console.print(
        f"rate {t.rate_hz:.1f} Hz (x{t.arm_speed:.2f} arm speed), period jitter "
        f"{t.period_jitter_s * 1e3:.2f} ms (max {t.period_jitter_max_s * 1e3:.2f}), state age "
        f"p50 {t.state_age_p50_s * 1e3:.2f} / p99 {t.state_age_p99_s * 1e3:.2f} ms, latency "
        f"p50 {t.latency_p50_s * 1e3:.2f} / p99 {t.latency_p99_s * 1e3:.2f} ms, missed "
        f"deadlines {t.missed_deadlines}, skipped states {t.skipped_states}, partial states "
        f"{t.partial_states}, incomplete ticks {t.incomplete_ticks}, CPU "
        f"{t.cpu_per_step_s * 1e6:.0f} us/step (process {t.process_cpu_per_step_s * 1e6:.0f})"
    )
    console.print(
        f"saturated steps {s.saturated_steps}, barrier cuts {s.barrier_steps}, stopped by "
        f"{s.stopped_by}"
    )


def cmd_run(args: argparse.Namespace, console: Console) -> Exit:
    params = dict(args.param)
    controller = load_controller(args.controller, **params)
    period, mismatch = control_period(controller, args.period)
    if mismatch:
        Console(stderr=True, highlight=False).print(f"[yellow]warning[/]: {mismatch}")
    hook: Callable[[StepRecord], None] | None = None
    finish: Callable[[ControlSummary | None, str | None], None] | None = None
    client = _connect(args, console)
    summary: ControlSummary | None = None
    error: str | None = None
    try:
        target = np.array(args.target, dtype=float)
        for dev, value in zip(JOINTS, target, strict=True):
            client.guard.check(dev, LimitKind.POSITION, float(value))
        faults = _blocking_faults(client.read_status(JOINTS), console)
        if faults:
            raise ArmFaultError(f"arm reports faults, not starting: {faults}")
        if args.record:
            meta: dict[str, object] = {
                "controller": args.controller,
                "params": params,
                "port": args.port,
                "period_s": period,
                "pacing": args.pacing,
                "target": target.tolist(),
                "seconds": args.seconds,
            }
            hook, finish = _recorder_hook(args.record, meta)
        loop = ControlLoop(client, controller, period, pacing=args.pacing, on_step=hook)
        try:
            summary = loop.run(target, args.seconds)
        except KeyboardInterrupt:
            error = "interrupted"
            raise
        error = summary.error
        _print_summary(console, summary)
        _print_metrics(console, summary)
        console.print(f"arm left in {summary.left_in}")
        if args.record:
            console.print(
                f"recorded {args.record}: open it with `rerun {args.record}`, "
                f"summarise it with `reach-driver inspect {args.record}`",
                soft_wrap=True,  # keep the commands copyable
            )
        if summary.error:
            console.print(f"[red]run failed[/]: {summary.error}")
            return Exit.FAILED
        return Exit.OK
    finally:
        if finish is not None:
            finish(summary, error)
        client.close()


def cmd_controllers(args: argparse.Namespace, console: Console) -> Exit:
    for name in available_controllers():
        console.print(name)
    return Exit.OK


def cmd_inspect(args: argparse.Namespace, console: Console) -> Exit:
    from reach_driver.rrd_summary import RecordingReadError, summarize_recording

    try:
        summary: dict[str, Any] = summarize_recording(args.file)
    except (RecordingReadError, OSError) as exc:
        console.print(f"[red]error[/]: cannot read {args.file}: {exc}")
        return Exit.FAILED
    if args.json:
        console.print_json(json.dumps(summary, default=float))
        return Exit.OK
    clean = "" if summary.get("closed_cleanly", True) else " [yellow](not closed cleanly: the "\
        "writer stopped early; everything before that is shown)[/]"
    console.print(f"[bold]{summary['file']}[/]: {summary['steps']} steps, "
                  f"{float(summary['duration_s']):.2f} s{clean}")
    joints = Table(title="final state (rad)")
    for col in ("joint", "target", "position", "error"):
        joints.add_column(col, justify="right")
    for row in zip(summary["joints"], summary["final_target"], summary["final_position"],
                   summary["final_error"], strict=True):
        joints.add_row(row[0], *(f"{float(v):+.4f}" for v in row[1:]))
    console.print(joints)
    metrics = summary.get("metrics")
    if isinstance(metrics, dict):
        table = Table(title="metrics (docs/metrics.md)")
        for key in metrics:
            table.add_column(key, justify="right")
        table.add_row(*(("yes" if v else "no") if isinstance(v, bool) else f"{float(v):.4g}"
                        for v in metrics.values()))
        console.print(table)
    for line in summary.get("events", []):
        console.print(f"  {line}")
    return Exit.OK


COMMANDS: dict[str, Callable[[argparse.Namespace, Console], Exit]] = {
    "info": cmd_info,
    "monitor": cmd_monitor,
    "move": cmd_move,
    "run": cmd_run,
    "controllers": cmd_controllers,
    "inspect": cmd_inspect,
}


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if hasattr(args, "max_current"):
        try:
            _safety(args)
        except ValueError as exc:
            parser.error(str(exc))  # exit 2 with the usage line
    # Piped output is not squeezed to 80 columns: tables stay one line per joint.
    console = Console(highlight=False, width=None if sys.stdout.isatty() else 160)
    errors = Console(stderr=True, highlight=False)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.ERROR,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    previous = signal.getsignal(signal.SIGTERM)
    if previous is signal.SIG_DFL and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_interrupt)  # terminate leaves the arm safe too
    try:
        return int(COMMANDS[args.command](args, console))
    except KeyboardInterrupt:
        errors.print("interrupted: arm left in a safe mode, link closed")
        return int(Exit.INTERRUPTED)
    except LimitError as exc:
        errors.print(f"[red]limit[/]: {exc}")
        return int(Exit.LIMIT)
    except BadUrlError as exc:
        errors.print(f"[red]error[/]: {exc}")
        return int(Exit.USAGE)
    except (PortNotFoundError, PortPermissionError, GarbageError, NoResponseError) as exc:
        errors.print(f"[red]no arm[/]: {exc}")
        return int(Exit.NO_ARM)
    except TransportError as exc:
        errors.print(f"[red]no arm[/]: {exc}")
        return int(Exit.NO_ARM)
    except (LinkDownError, DriverError) as exc:
        errors.print(f"[red]failed[/]: {exc}")
        return int(Exit.FAILED)
    finally:
        if signal.getsignal(signal.SIGTERM) is _raise_interrupt:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


if __name__ == "__main__":
    sys.exit(main())
