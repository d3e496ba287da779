"""How the CLI shows things: the info and monitor tables, run summaries, metrics, recordings."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from protocol import DeviceID, Mode, PacketID
from protocol.alpha5 import JAW, JOINT_LETTERS, JOINTS, TORQUE_PER_AMP_NM
from reach_driver.cli.report import run_metrics
from reach_driver.client import ArmClient
from reach_driver.faults import blocking_flags, flag_labels, status_bytes
from reach_driver.metrics import METRIC_KEYS
from reach_driver.records import ControlSummary
from reach_driver.safety import LimitKind
from reach_driver.state import JointState, joint_name

LINK_FLAGS = frozenset({"SERIAL_ERROR", "CRC_ERROR"})


def fmt(value: float | None, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def limit_range(js: JointState, kind: LimitKind) -> str:
    reading = getattr(js, f"{kind.value}_limits")
    if reading is None:
        return "-"
    lo, hi = reading.value
    return f"{lo:.4g} .. {hi:.4g}"


def mode_name(js: JointState) -> str:
    if js.mode is None:
        return "-"
    value = js.mode.value
    return value.name.lower() if isinstance(value, Mode) else f"0x{value:02X}"


def info_json(port: str, joints: dict[int, JointState]) -> dict[str, Any]:
    out = {}
    for dev, js in joints.items():
        out[DeviceID(dev).name] = {
            "device": dev,
            "mode": mode_name(js),
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
            "status": status_bytes(js.status.value) if js.status else None,
            "blocking_flags": flag_labels(blocking_flags(js.status.value)) if js.status else [],
            "diagnostics": diagnostics_json(js),
        }
    return {"port": port, "devices": out}


def info_table(port: str, joints: dict[int, JointState]) -> Table:
    table = Table(title=f"Reach arm on {port}: {len(joints)} device(s)")
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
        table.add_row(
            joint_name(dev),
            mode_name(js),
            js.software_version.value if js.software_version else "-",
            fmt(js.serial_number.value, 0) if js.serial_number else "-",
            fmt(js.model_number.value, 0) if js.model_number else "-",
            fmt(js.position.value) if js.position else "-",
            limit_range(js, LimitKind.POSITION),
            limit_range(js, LimitKind.VELOCITY),
            limit_range(js, LimitKind.CURRENT),
            status_text(js),
        )
    return table


#: The Monitor readings (docs/protocol.md 3a): column title, (JointState field, digits).
DIAGNOSTIC_COLUMNS: tuple[tuple[str, tuple[str, int]], ...] = (
    ("supply V", ("voltage", 2)),
    ("temp degC", ("temperature", 1)),
    ("humidity %", ("humidity", 1)),
    ("pressure bar", ("internal_pressure", 3)),
)


def diagnostic_cells(js: JointState) -> list[str]:
    cells = []
    for _, (name, digits) in DIAGNOSTIC_COLUMNS:
        reading = getattr(js, name)
        cells.append(fmt(reading.value, digits) if reading is not None else "-")
    return cells


def diagnostics_json(js: JointState) -> dict[str, Any]:
    """The Monitor readings with their units in the keys (None where not reported)."""

    def value(reading: Any) -> Any:
        return None if reading is None else reading.value

    climate = value(js.factory_climate)
    return {
        "voltage_v": value(js.voltage),
        "temperature_c": value(js.temperature),
        "humidity_pct": value(js.humidity),
        "internal_pressure_bar": value(js.internal_pressure),
        "factory_climate": None if climate is None else climate._asdict(),
    }


def diagnostics_table(port: str, joints: dict[int, JointState]) -> Table:
    """`info`'s second table: each device's Monitor readings beside its factory climate."""
    table = Table(title=f"diagnostics on {port} (live; factory climate at assembly)")
    table.add_column("device")
    for column, _ in DIAGNOSTIC_COLUMNS:
        table.add_column(column, justify="right")
    table.add_column("factory degC / bar / %", justify="right")
    for dev, js in joints.items():
        climate = js.factory_climate.value if js.factory_climate else None
        table.add_row(
            joint_name(dev),
            *diagnostic_cells(js),
            "-"
            if climate is None
            else f"{climate.temperature_c:.1f} / {climate.pressure_bar:.3f} / "
            f"{climate.humidity_pct:.1f}",
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
    for column, _ in DIAGNOSTIC_COLUMNS:
        table.add_column(column, justify="right")
    table.add_column("status")
    for dev in (*JOINTS, JAW):
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


def blocking_faults(flags: dict[int, list[str]], console: Console | None) -> str:
    """Status flags that must stop a move, as text ('' if none). Link error flags (a CRC or
    serial error the arm saw on the line) are only reported: they say nothing about the
    motors, and the arm clears them by itself."""
    blocking = []
    for dev, names in flags.items():
        link = [n for n in names if n in LINK_FLAGS]
        other = [n for n in names if n not in LINK_FLAGS]
        if link and console is not None:
            console.print(
                f"[yellow]warning[/]: {joint_name(dev)} reports {escape(', '.join(link))}"
            )
        if other:
            blocking.append(f"{joint_name(dev)}: {', '.join(other)}")
    return "; ".join(blocking)


METRIC_LABELS = {
    "energy_j": ("energy", "J"),
    "rmse": ("RMSE", "rad"),
    "mie": ("MIE", "rad s"),
    "msse": ("MSSE", "rad"),
    "overshoot_pct": ("overshoot", "%"),
    "settling_time_s": ("settling time", "s"),
    "reached": ("reached", ""),
}


def print_metrics(console: Console, s: ControlSummary) -> None:
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
        cells.append(
            ("yes" if value else "[red]no[/]") if isinstance(value, bool) else f"{float(value):.4g}"
        )
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


def print_summary(console: Console, s: ControlSummary) -> None:
    table = Table(title=f"run: {s.steps} steps, {s.loop_seconds:.2f} s loop time")
    for column in ("joint", "target", "final", "error"):
        table.add_column(column, justify="right")
    for j, tgt, q, e in zip(JOINT_LETTERS, s.target, s.final_q, s.final_error, strict=True):
        table.add_row(j, fmt(tgt), fmt(q), fmt(e))
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
    joints = Table(title="final state (rad)")
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
    console.print(joints)
    metrics = summary.get("metrics")
    if isinstance(metrics, dict):
        table = Table(title="metrics (docs/metrics.md)")
        for key in metrics:
            table.add_column(key, justify="right")
        table.add_row(
            *(
                ("yes" if v else "no") if isinstance(v, bool) else f"{float(v):.4g}"
                for v in metrics.values()
            )
        )
        console.print(table)
    for line in summary.get("events", []):
        console.print(f"  {escape(str(line))}")
