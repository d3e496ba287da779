"""How the CLI shows things: the info and monitor tables, run summaries, metrics, recordings,
the registered controllers."""

from __future__ import annotations

import math
import shutil
import sys
import textwrap
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from protocol import DeviceID, HardwareStatus, Mode, PacketID
from protocol.models import ALPHA5, ArmModel, model_named
from reach_driver.cli.exits import for_operator
from reach_driver.cli.report import run_metrics, run_overshoot
from reach_driver.cli.tables import show_table
from reach_driver.client import ArmClient
from reach_driver.controllers import ControllerInfo, ControllerKind
from reach_driver.drawing import ArmDrawing
from reach_driver.faults import blocking_flags, flag_labels, status_bytes
from reach_driver.ik import ChainSolution, Envelope, Solution, xyz_text
from reach_driver.metrics import METRIC_KEYS, metric_label
from reach_driver.records import ControlSummary
from reach_driver.safety import LimitKind
from reach_driver.state import MONITOR_READINGS, JointState, joint_name


def as_typed(program: str) -> str:
    """How the user types one of this install's programs (`rerun`, `reach-driver`): bare when
    it is on PATH, else its path beside this interpreter (a venv not activated, as after
    `make demo`), relative when under the working directory. Every hint names it this way."""
    if shutil.which(program):
        return program
    beside = Path(sys.executable).with_name(program)
    if not beside.is_file():
        return program
    try:
        return str(beside.relative_to(Path.cwd()))
    except ValueError:
        return str(beside)


def fmt(value: float | None, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def limit_range(js: JointState, kind: LimitKind) -> str:
    reading = getattr(js, f"{kind.value}_limits")
    if reading is None:
        return "-"
    lo, hi = reading.value
    if math.isclose(lo, -hi, rel_tol=1e-6) and hi > 0:
        return f"±{hi:.6g}"
    return f"{lo:.6g} .. {hi:.6g}"


def mode_name(js: JointState) -> str:
    if js.mode is None:
        return "-"
    value = js.mode.value
    return value.name.lower() if isinstance(value, Mode) else f"0x{value:02X}"


def sig6(value: float) -> float:
    """`value` to 6 significant digits: the arm sends float32, whose tail is noise."""
    return float(f"{value:.6g}")


def jsonable(value: Any, digits6: bool = False) -> Any:
    """Plain JSON types: numpy arrays and scalars to lists and numbers, NaN/inf to null,
    floats to 6 significant digits if asked."""
    if isinstance(value, dict):
        return {str(k): jsonable(v, digits6) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [jsonable(v, digits6) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        if not math.isfinite(f):
            return None
        return sig6(f) if digits6 else f
    return value


def _whole(reading: Any) -> int | None:
    """A serial or model number: the arm sends it as a float; it is a whole number."""
    if reading is None or not math.isfinite(float(reading.value)):
        return None
    return int(round(float(reading.value)))


def info_json(port: str, joints: dict[int, JointState], model: ArmModel = ALPHA5) -> dict[str, Any]:
    out = {}
    for dev, js in joints.items():
        out[DeviceID(dev).name] = {
            "device": dev,
            "mode": mode_name(js),
            "software_version": js.software_version.value if js.software_version else None,
            "serial_number": _whole(js.serial_number),
            "model_number": _whole(js.model_number),
            "position": js.position.value if js.position else None,
            "limits": {
                kind.value: list(getattr(js, f"{kind.value}_limits").value)
                for kind in LimitKind
                if getattr(js, f"{kind.value}_limits") is not None
            },
            "status_flags": js.fault_names,
            "status": status_bytes(js.status.value) if js.status else None,
            "blocking_flags": flag_labels(blocking_flags(js.status.value)) if js.status else [],
            "diagnostics": diagnostics_json(js),
        }
    return jsonable({"port": port, "arm": model.name, "devices": out}, digits6=True)


def info_tables(
    port: str, joints: dict[int, JointState], model: ArmModel = ALPHA5
) -> tuple[Table, Table]:
    """Two tables that each fit 80 columns: who answers, and where and within what limits.
    The Alpha 5's title says "Reach arm", as it always has; another model's names it."""
    arm = "Reach arm" if model is ALPHA5 else model.title
    ids = Table(title=f"{arm} on {escape(port)}: {len(joints)} device(s)")
    for column in ("device", "mode", "version", "serial no.", "model no.", "status"):
        ids.add_column(column)
    limits = Table(
        title="position and limits",
        caption=f"joints {' '.join(model.joint_letters)} in rad and rad/s, the jaw "
        f"{model.jaw.name} in {model.jaw_unit} and {model.jaw_unit}/s",
        show_edge=False,
    )
    for column in ("device", "position", "position limits", "velocity limit", "current limit"):
        limits.add_column(column, justify="right", no_wrap=True)
    for dev, js in joints.items():
        serial, number = _whole(js.serial_number), _whole(js.model_number)
        ids.add_row(
            joint_name(dev),
            mode_name(js),
            escape(str(js.software_version.value)) if js.software_version else "-",
            "-" if serial is None else str(serial),
            "-" if number is None else str(number),
            status_text(js),
        )
        pos_unit = model.unit(dev)
        vel_unit = f"{pos_unit}/s"
        limits.add_row(
            joint_name(dev),
            f"{fmt(js.position.value)} {pos_unit}" if js.position else "-",
            _with_unit(limit_range(js, LimitKind.POSITION), pos_unit),
            _with_unit(limit_range(js, LimitKind.VELOCITY), vel_unit),
            _with_unit(limit_range(js, LimitKind.CURRENT), "mA"),
        )
    return ids, limits


def _with_unit(text: str, unit: str) -> str:
    return text if text == "-" else f"{text} {unit}"


def monitor_json(
    client: ArmClient, rates: dict[tuple[int, int], float], t: float
) -> dict[str, Any]:
    """One `monitor --json` line: the state of every device and the link's counters."""
    now = client.clock()
    state = client.state
    devices = {}
    for dev in client.model.actuators:
        js = state.joint(dev)
        devices[DeviceID(dev).name] = {
            "mode": mode_name(js) if js.mode is not None else None,
            "position": js.position.value if js.position else None,
            "velocity": js.velocity.value if js.velocity else None,
            "current_mA": js.current.value if js.current else None,
            "age_s": js.position.age(now) if js.position else None,
            "rate_hz": rates.get((int(dev), int(PacketID.POSITION))),
            "status": status_bytes(js.status.value) if js.status else None,
            "diagnostics": diagnostics_json(js),
        }
    ts, ds, cs = client.transport.stats, client.decoder_stats, client.stats
    return jsonable(
        {
            "t": t,
            "link": client.link_state.value,
            "devices": devices,
            "bytes_in": ts.bytes_in,
            "bytes_out": ts.bytes_out,
            "good_frames": ds.good_frames,
            "bad_frames": ds.bad_total,
            "bad_frames_by_reason": {r.value: n for r, n in ds.bad_frames.items() if n},
            "discarded_bytes": ds.bytes_discarded,
            "reconnects": cs.reconnects,
            "request_timeouts": cs.request_timeouts,
        },
        digits6=True,
    )


def diagnostic_cells(js: JointState) -> list[str]:
    cells = []
    for m in MONITOR_READINGS:
        reading = getattr(js, m.field)
        cells.append(fmt(reading.value, m.digits) if reading is not None else "-")
    return cells


def diagnostics_json(js: JointState) -> dict[str, Any]:
    """The Monitor readings with their units in the keys (None where not reported)."""
    out: dict[str, Any] = {}
    for m in MONITOR_READINGS:
        reading = getattr(js, m.field)
        out[m.key] = None if reading is None else reading.value
    climate = js.factory_climate
    out["factory_climate"] = None if climate is None else climate.value._asdict()
    return out


def diagnostics_table(port: str, joints: dict[int, JointState]) -> Table:
    """`info`'s second table: each device's Monitor readings beside its factory climate."""
    table = Table(
        title=f"diagnostics on {port}",
        caption="live readings; pressure: 0x67 as V1.12.1 has it, 0x6E as the newer SDK has it; "
        "factory: the climate sealed in at assembly (degC/bar/%)",
    )
    table.add_column("device", no_wrap=True)
    for m in MONITOR_READINGS:
        table.add_column(m.column, justify="right")
    table.add_column("factory", justify="right")
    for dev, js in joints.items():
        climate = js.factory_climate.value if js.factory_climate else None
        table.add_row(
            joint_name(dev),
            *diagnostic_cells(js),
            "-"
            if climate is None
            else f"{climate.temperature_c:.0f}/{climate.pressure_bar:.2f}/"
            f"{climate.humidity_pct:.0f}",
        )
    return table


def status_text(js: JointState) -> str:
    """HARDWARE_STATUS by byte, one line each ('C: ENCODER_FAULT'): red if any flag blocks
    the joint (reach_driver.faults), yellow if all are informational."""
    if js.status is None:
        return "-"
    named = [f"{b}: {', '.join(n)}" for b, n in status_bytes(js.status.value).items() if n]
    if not named:
        return "ok"
    colour = "red" if blocking_flags(js.status.value) else "yellow"
    return f"[{colour}]" + escape("\n".join(named)) + "[/]"


def monitor_table(client: ArmClient, rates: dict[tuple[int, int], float], port: str) -> Table:
    now = client.clock()
    state = client.state
    table = Table(title=f"{port}: link {client.link_state.value}")
    for column in ("joint", "mode", "position", "velocity", "current mA", "age ms", "rate Hz"):
        table.add_column(column, justify="right")
    for m in MONITOR_READINGS:
        table.add_column(m.column, justify="right")
    table.add_column("status")
    for dev in client.model.actuators:
        js = state.joint(dev)
        age = js.position.age(now) * 1e3 if js.position else math.nan
        table.add_row(
            joint_name(dev),
            mode_name(js),
            fmt(js.position.value if js.position else None),
            fmt(js.velocity.value if js.velocity else None),
            fmt(js.current.value if js.current else None, 1),
            fmt(age, 0),
            fmt(rates.get((int(dev), int(PacketID.POSITION)), math.nan), 1),
            *diagnostic_cells(js),
            status_text(js),
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


#: What a line says for a value not measured yet (never "nan").
UNMEASURED = "--"


def measured(value: float | None, spec: str) -> str:
    """`value` formatted by `spec`, or UNMEASURED if there is none yet (None, NaN, inf)."""
    if value is None or not math.isfinite(value):
        return UNMEASURED
    text = f"{value:{spec}}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # no "-0"


def monitor_line(client: ArmClient, rates: dict[tuple[int, int], float], t: float) -> str:
    """`monitor` off a terminal: a plain line of every device's angle, current, update rate,
    mode and status flags and the link's frames; the table at the end has the rest."""
    state = client.state
    devices = client.model.actuators
    joints = [state.joint(dev) for dev in devices]
    names = [DeviceID(dev).name for dev in devices]
    position = " ".join(
        f"{n} {measured(js.position.value if js.position else None, '.4f')}"
        for n, js in zip(names, joints, strict=True)
    )
    current = " ".join(
        f"{n} {measured(js.current.value if js.current else None, '.0f')}"
        for n, js in zip(names, joints, strict=True)
    )
    rate = " ".join(
        f"{n} {measured(rates.get((int(dev), int(PacketID.POSITION))), '.0f')}"
        for n, dev in zip(names, devices, strict=True)
    )
    modes = {mode_name(js) for js in joints}
    mode = (
        modes.pop()
        if len(modes) == 1
        else " ".join(f"{n} {mode_name(js)}" for n, js in zip(names, joints, strict=True))
    )
    flagged = []
    for n, js in zip(names, joints, strict=True):
        by_byte = status_bytes(js.status.value) if js.status is not None else {}
        named = [f"{b}: {', '.join(flags)}" for b, flags in by_byte.items() if flags]
        if named:
            flagged.append(f"{n} {' '.join(named)}")
    ds = client.decoder_stats
    parts = [
        f"t {t:5.1f} s",
        f"link {client.link_state.value}",
        f"position [rad, A mm] {position}",
        f"current [mA] {current}",
        f"rate [Hz] {rate}",
        f"mode {mode}",
        f"status {'; '.join(flagged) if flagged else 'ok'}",
        f"frames {ds.good_frames} ok {ds.bad_total} bad",
    ]
    return " | ".join(parts)


def blocking_faults(flags: dict[int, list[str]], console: Console | None) -> str:
    """Status flags that must stop a move, as text ('' if none), by the one policy in
    `reach_driver.faults`: the others (link errors the arm saw on the line, a service
    reminder, read protection...) are only reported."""
    blocking = []
    for dev, names in flags.items():
        status = HardwareStatus.NONE
        for name in names:
            if name in HardwareStatus.__members__:
                status |= HardwareStatus[name]
        stops = flag_labels(blocking_flags(status))
        unknown = [n for n in names if n not in HardwareStatus.__members__]
        stops += unknown  # a name this driver cannot place is treated as blocking
        shown = [n for n in names if n not in stops]
        if shown and console is not None:
            console.print(
                f"[yellow]warning[/]: {joint_name(dev)} reports {escape(', '.join(shown))}"
            )
        if stops:
            blocking.append(f"{joint_name(dev)}: {', '.join(stops)}")
    return "; ".join(blocking)


# One name and unit per metric, for every table that shows one (run, inspect). Belongs next to
# reach_driver.metrics.METRIC_KEYS; a key without a label is shown by its key.
def metrics_table(title: str, values: dict[str, Any]) -> Table:
    """The metrics a row each, in METRIC_KEYS order (then any others): name with unit, value,
    and the key --json gives it. Three columns, so it fits 80 however many metrics there are."""
    keys = [k for k in METRIC_KEYS if k in values] + [k for k in values if k not in METRIC_KEYS]
    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("--json key")
    for key in keys:
        value = values[key]
        if isinstance(value, bool):
            cell = "yes" if value else "[red]no[/]"
        elif isinstance(value, (int, float)):
            cell = f"{float(value):.4g}"
        else:
            cell = escape(str(value))
        table.add_row(escape(metric_label(key)), cell, escape(key))
    return table


def overshoot_line(overshoot: dict[str, Any] | None) -> str:
    """How the worst joint's overshoot came about (docs/metrics.md, "Overshoot")."""
    if not overshoot:
        return "overshoot: no joint went past its goal"
    how = (
        "carried through by its approach"
        if overshoot["arrival"]
        else "across slowly, near its goal"
    )
    return (
        f"overshoot: {overshoot['joint']} went {1000 * float(overshoot['past_rad']):.1f} mrad "
        f"({float(overshoot['pct']):.2f} % of its step) past its goal at "
        f"{float(overshoot['peak_s']):.2f} s, crossing it at "
        f"{float(overshoot['crossing_speed']):.3f} rad/s: {how}"
    )


def print_metrics(console: Console, s: ControlSummary) -> None:
    metrics = run_metrics(s)
    if metrics is None:
        console.print("metrics: none (fewer than two states were seen)")
        return
    show_table(
        console,
        metrics_table("metrics (docs/metrics.md; from the reported angles)", metrics.as_dict()),
    )
    anatomy = run_overshoot(s)
    console.print(escape(overshoot_line(None if anatomy is None else anatomy.as_dict())))
    tr = s.trace
    assert tr is not None
    measured = int(np.isfinite(tr.current_mA[1:]).all(axis=1).sum())
    kt = "/".join(f"{k:.3g}" for k in s.model.torque_per_amp_nm)
    source = "commanded" if measured == 0 else "measured"
    note = f"torque = {source} current x {kt} N m/A ({' '.join(s.model.joint_letters)})"
    if 0 < measured < tr.samples - 1:
        note += f" (commanded on the {tr.samples - 1 - measured} samples without a reading)"
    if tr.filled:
        note += f"; {tr.filled} incomplete states interpolated"
    console.print(note)


def print_summary(console: Console, s: ControlSummary) -> None:
    table = Table(title=f"run: {s.steps} steps, {s.loop_seconds:.2f} s loop time")
    for column in ("joint", "target [rad]", "final [rad]", "error [rad]"):
        table.add_column(escape(column), justify="right")
    letters = s.model.joint_letters
    for j, tgt, q, e in zip(letters, s.target, s.final_q, s.final_error, strict=True):
        table.add_row(j, fmt(tgt), fmt(q), fmt(e))
    show_table(console, table)
    t = s.timing
    console.print(
        f"rate {t.rate_hz:.1f} Hz (x{t.arm_speed:.2f} arm speed), period jitter "
        f"{t.period_jitter_s * 1e3:.2f} ms (max {t.period_jitter_max_s * 1e3:.2f}), state age "
        f"p50 {t.state_age_p50_s * 1e3:.2f} / p99 {t.state_age_p99_s * 1e3:.2f} ms, latency "
        f"p50 {t.latency_p50_s * 1e3:.2f} / p99 {t.latency_p99_s * 1e3:.2f} ms, missed "
        f"deadlines {t.missed_deadlines}, skipped states {t.skipped_states}, partial states "
        f"{t.partial_states}, incomplete ticks {t.incomplete_ticks}, stream gaps "
        f"{t.stream_gaps} (up to {t.lost_ticks} ticks not counted), CPU "
        f"{t.cpu_per_step_s * 1e6:.0f} us/step (process {t.process_cpu_per_step_s * 1e6:.0f})"
    )
    gaps = t.gaps
    longest = f"; longest: {gaps.longest[0].describe()}" if gaps.longest else ""
    console.print(escape(f"{gaps.brief()}; {t.realtime.describe()}{longest}"))
    console.print(
        f"saturated steps {s.saturated_steps}, barrier cuts {s.barrier_steps}, implausible "
        f"samples {s.implausible_samples}, duplicate packets {s.duplicate_packets}, stream "
        f"{'unmeasured' if s.measured_hz is None else f'{s.measured_hz:.3g} Hz'}, stopped by "
        f"{escape(for_operator(s.stopped_by))}"
    )


def print_recording(console: Console, summary: dict[str, Any]) -> None:
    """A recording's summary (`reach-driver inspect`)."""
    if summary.get("truncated"):
        clean = (
            f" [yellow](truncated: the file ends inside a message; the last "
            f"{summary.get('truncated_bytes', 0)} bytes were skipped, everything before them "
            "is shown)[/]"
        )
    elif not summary.get("closed_cleanly", True):
        clean = (
            " [yellow](not closed cleanly: the writer stopped early; everything before that "
            "is shown)[/]"
        )
    else:
        clean = ""
    if summary.get("kind") == "simulator":
        print_sim_recording(console, summary, clean)
        return
    console.print(
        f"[bold]{escape(str(summary['file']))}[/]: {summary['steps']} steps, "
        f"{float(summary['duration_s']):.2f} s{clean}"
    )
    if not summary["steps"]:
        meta = summary.get("metadata") or {}
        about = ", ".join(
            f"{key} {meta[key]}"
            for key in ("controller", "port", "target", "seconds", "period_s")
            if key in meta
        )
        console.print(
            "recorded by reach-stack, but no steps: the run ended (or was killed) before its "
            f"first step{': ' + escape(about) if about else ''}",
            soft_wrap=True,
        )
        for line in summary.get("events", []):
            console.print(f"  {escape(str(line))}")
        return
    arm = summary.get("arm", ALPHA5.name)
    named = "" if arm == ALPHA5.name else f" of the {_model_title(str(arm))}"
    joints = Table(title=f"final state{named} (rad)")
    for col in ("joint", "target", "position", "error"):
        joints.add_column(col, justify="right")
    for row in zip(
        summary["joints"],
        summary["final_target"],
        summary["final_position"],
        summary["final_error"],
        strict=True,
    ):
        joints.add_row(row[0], *(f"{float(v):+.4f}" for v in row[1:]))
    show_table(console, joints)
    metrics = summary.get("metrics")
    if isinstance(metrics, dict):
        show_table(console, metrics_table("metrics (docs/metrics.md)", metrics))
        console.print(escape(overshoot_line(summary.get("overshoot"))))
    for note in summary.get("notes", []):
        console.print(escape(str(note)), soft_wrap=True)
    diagnostics = summary.get("diagnostics")
    if isinstance(diagnostics, dict):
        show_table(console, recorded_diagnostics_table(diagnostics))
    for line in summary.get("events", []):
        console.print(f"  {escape(str(line))}")


def _model_title(name: str) -> str:
    try:
        return model_named(name).title
    except ValueError:
        return name


def recorded_diagnostics_table(diagnostics: dict[str, Any]) -> Table:
    """`inspect`: each device's last Monitor readings and status flags in the recording."""
    table = Table(
        title="diagnostics (last reading of each device)",
        caption="--json adds each reading's min and max over the recording",
    )
    table.add_column("device")
    shown = [m for m in MONITOR_READINGS if m.key in diagnostics]
    for m in shown:
        table.add_column(m.column, justify="right")
    table.add_column("status")
    status = diagnostics.get("final_status") or {}
    for i, letter in enumerate(diagnostics["devices"]):
        cells = []
        for m in shown:
            value = diagnostics[m.key]["final"][i]
            cells.append("-" if value is None else fmt(value, m.digits))
        flags = status.get(letter)
        table.add_row(letter, *cells, "-" if flags is None else escape(", ".join(flags)))
    return table


def print_sim_recording(console: Console, summary: dict[str, Any], clean: str) -> None:
    """A simulator recording (`reach-sim --record`): the true state; it has no targets."""
    part = summary.get("part")
    span = (
        f", sim time {float(summary['start_s']):.2f}..{float(summary['end_s']):.2f} s"
        if summary.get("start_s") is not None
        else ""
    )
    console.print(
        f"[bold]{escape(str(summary['file']))}[/]: simulator recording (reach-sim --record, the "
        f"arm's true state; no targets), {summary['steps']} samples, "
        f"{float(summary['duration_s']):.2f} s{span}"
        f"{f', part {part} of a rotated recording' if part else ''}{clean}",
        soft_wrap=True,
    )
    arm = summary.get("arm", ALPHA5.name)
    named = "" if arm == ALPHA5.name else f" of the {_model_title(str(arm))}"
    joints = Table(title=f"final true state{named}")
    for col in ("joint", "mode", "position (rad)", "setpoint (rad)"):
        joints.add_column(col, justify="right")
    for j, mode, q, sp in zip(
        summary["joints"],
        summary["final_modes"],
        summary["final_position"],
        summary["final_setpoint"],
        strict=True,
    ):
        joints.add_row(
            j,
            escape(str(mode or "?")),
            "-" if q is None else f"{float(q):+.4f}",
            "-" if sp is None else f"{float(sp):+.4f}",
        )
    show_table(console, joints)
    console.print(f"faults at the end: {escape(str(summary.get('final_faults', 'none')))}")
    for line in summary.get("events", []):
        console.print(f"  {escape(str(line))}")


class Roles(NamedTuple):
    """What each joint of a model does to the tool centre point (`ArmDrawing.positioning`):
    the first sets its bearing, `moving` (the first included) place it, `free` only turn
    the tool about its own axis."""

    letters: tuple[str, ...]
    moving: tuple[str, ...]
    free: tuple[str, ...]

    @classmethod
    def of(cls, model: ArmModel, drawing: ArmDrawing) -> Roles:
        letters = model.joint_letters
        moving = tuple(letters[i] for i in drawing.positioning)
        return cls(letters, moving, tuple(j for j in letters if j not in moving))

    @property
    def free_text(self) -> str:
        return " ".join(self.free)


def workspace_tables(env: Envelope, margin: float, roles: Roles) -> tuple[Table, Table]:
    """`workspace`: the envelope (mm) and the position limits it was found within."""
    reach = Table(title="where the tool centre point reaches (mm, base frame, as move --xyz)")
    for column in ("", "min", "max"):
        reach.add_column(column, justify="left" if not column else "right")
    x, y = env.axis_mm
    axis = (
        "the base's z axis"
        if math.hypot(x, y) < 1e-6
        else f"{roles.moving[0]}'s axis (at x {x:.1f} y {y:.1f})"
    )
    reach.add_row(f"distance from {axis}", *(f"{v:.1f}" for v in env.radius_mm))
    reach.add_row("height z", *(f"{v:.1f}" for v in env.z_mm))
    reach.add_row("distance from the base's origin", "-", f"{env.reach_mm:.1f}")
    reach.caption = f"{roles.moving[0]} sets the bearing" + (
        f"; {roles.free_text} turns the tool about its own axis, never moving it"
        if roles.free
        else ""
    )
    source = "factory" + (f" less --position-margin {margin:g}" if margin else "")
    limits = Table(title=f"position limits used ({source})")
    for column in ("joint", "min [rad]", "max [rad]", "min [deg]", "max [deg]"):
        limits.add_column(escape(column), justify="right")
    for letter, (lo, hi) in zip(roles.letters, env.limits, strict=True):
        limits.add_row(
            letter, f"{lo:.4f}", f"{hi:.4f}", f"{math.degrees(lo):.1f}", f"{math.degrees(hi):.1f}"
        )
    return reach, limits


def _moving_angles(roles: Roles, q: np.ndarray) -> dict[str, float]:
    return {j: float(v) for j, v in zip(roles.letters, q, strict=True) if j in roles.moving}


def workspace_point_line(
    xyz: tuple[float, float, float], sol: Solution | ChainSolution, roles: Roles
) -> str:
    """`workspace --xyz`: the angles for the point, or the nearest reachable point's."""
    angles = " ".join(f"{j} {v:.4f}" for j, v in _moving_angles(roles, sol.q).items())
    free = f" ({roles.free_text} any angle)" if roles.free else ""
    if sol.reachable:
        return f"{xyz_text(xyz)} mm is reachable at {angles} rad{free}"
    return (
        f"{xyz_text(xyz)} mm is out of reach; the nearest reachable point is "
        f"{xyz_text(sol.point_mm)} mm, {sol.error_mm:.1f} mm away, at {angles} rad{free}"
    )


def workspace_json(
    env: Envelope,
    margin: float,
    xyz: tuple[float, float, float] | None,
    sol: Solution | ChainSolution | None,
    roles: Roles,
) -> dict[str, Any]:
    """`workspace --json`: the envelope, the limits, the angles at each bound and, with
    --xyz, the point."""
    out: dict[str, Any] = {
        "radius_mm": list(env.radius_mm),
        "z_mm": list(env.z_mm),
        "reach_mm": env.reach_mm,
        "axis_mm": list(env.axis_mm),
        "bounds_angles_rad": {
            name: dict(zip(roles.letters, q.tolist(), strict=True)) for name, q in env.poses.items()
        },
        "position_limits_rad": {
            j: list(lim) for j, lim in zip(roles.letters, env.limits.tolist(), strict=True)
        },
        "position_margin_rad": margin,
    }
    if xyz is not None and sol is not None:
        out["target"] = {
            "xyz_mm": list(xyz),
            "reachable": sol.reachable,
            "point_mm": [round(float(v), 3) + 0.0 for v in sol.point_mm],  # no 1e-14
            "distance_mm": sol.error_mm,
            "angles_rad": _moving_angles(roles, sol.q),
        }
    return jsonable(out, digits6=True)


#: `reach-driver controllers` fits a terminal of this width
LISTING_WIDTH = 80


def _clip(text: str, width: int) -> str:
    """`text` in `width` columns, cut at a word with "..." if it is longer."""
    if len(text) <= width:
        return text
    return textwrap.shorten(text, width=width, placeholder="...")


def _value_text(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_value_text(v) for v in value)
    return str(value)


def _wrapped(label: str, text: str, indent: int) -> list[str]:
    first = " " * indent + f"{label}: "
    return textwrap.wrap(
        text or "-",
        width=LISTING_WIDTH,
        initial_indent=first,
        subsequent_indent=" " * (indent + 4),
        break_on_hyphens=False,
    )


def provenance_lines(provenance: dict[str, Any], indent: int = 4) -> list[str]:
    """A learned controller's provenance, a field a line (wrapped to 80 columns); a field
    holding records (e.g. its training stages) is counted here and given whole by --json."""
    lines: list[str] = []
    for key, value in provenance.items():
        nested = isinstance(value, dict) or (
            isinstance(value, (list, tuple)) and any(isinstance(v, dict) for v in value)
        )
        text = f"{len(value)} (each in --json)" if nested else _value_text(value)
        lines += _wrapped(str(key), text, indent)
    return lines


def controllers_lines(infos: list[ControllerInfo]) -> list[str]:
    """The registered controllers as a table in 80 columns (name, kind, summary cut to fit),
    each learned one's provenance indented below it, and any load error."""
    name_w = min(24, max([len("name"), *(len(i.name) for i in infos)]))
    kind_w = max(len(kind.value) for kind in ControllerKind)
    summary_w = LISTING_WIDTH - name_w - kind_w - 4
    lines = [f"{'name':<{name_w}}  {'kind':<{kind_w}}  summary"]
    if not infos:
        return [*lines, "(no controllers registered: is reach-stack installed? pip install -e .)"]
    for info in infos:
        if info.extra:
            summary = f"(not installed: needs the {info.extra} extra)"
        else:
            summary = info.summary or ("(failed to load)" if info.error else "(no docstring)")
        summary = _clip(summary.rstrip("."), summary_w)
        row = f"{info.name:<{name_w}}  {info.kind.value:<{kind_w}}  {summary}"
        lines.append(row.rstrip())
        if info.error:
            lines += _wrapped("missing" if info.extra else "error", info.error, 4)
        if info.provenance:
            lines += provenance_lines(info.provenance)
    return lines
