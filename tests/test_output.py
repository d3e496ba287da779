"""Output that reads anywhere: every table goes out through `reach_driver.cli.tables`, so a
number is never cut to fit. Piped, a table is plain aligned text a line per row; on a terminal
it is drawn when it fits and otherwise falls back to plain text in blocks of its width. A
piped `monitor` prints a plain line a second as it goes."""

from __future__ import annotations

import ast
import fcntl
import io
import json
import os
import queue
import re
import select
import signal
import struct
import subprocess
import sys
import termios
import threading
from pathlib import Path

import numpy as np
from conftest import WATCHDOG_S, default_sigint
from rich.console import Console
from rich.table import Table

from reach_driver.metrics import ALL_METRIC_KEYS, metric_label

ROOT = Path(__file__).resolve().parents[1]
CUT = "…"  # what rich puts where it cuts a cell
BOX = re.compile("[│┃━─┏┡└]")


def _env(**extra: str) -> dict[str, str]:
    """The child's environment: this tree first, no terminal settings inherited."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "NO_COLOR")}
    env = {k: v for k, v in env.items() if not k.startswith(("TTY_", "FORCE_COLOR"))}
    return {**env, "PYTHONPATH": str(ROOT), "TERM": "xterm-256color", **extra}


def _on_terminal(argv: list[str], columns: int) -> tuple[int, str]:
    """`argv` with its stdout on a pseudo-terminal `columns` wide: (exit status, what it
    showed, escape sequences and carriage returns taken out)."""
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, columns, 0, 0))
    proc = subprocess.Popen(
        argv, cwd=ROOT, stdout=slave, stderr=subprocess.PIPE, env=_env(COLUMNS=str(columns))
    )
    os.close(slave)
    chunks = []
    try:
        while select.select([master], [], [], 120.0)[0]:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
        code = proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        assert proc.stderr is not None
        proc.stderr.close()
    text = b"".join(chunks).decode("utf-8", "replace").replace("\r", "")
    return code, re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", text)


def _wide_table() -> tuple[Table, list[str]]:
    """Twelve columns of long numbers: more than 80 columns drawn."""
    values = [f"{12345.678 * (i + 1):.3f}" for i in range(12)]
    table = Table(title="wide")
    table.add_column("name")
    for i in range(12):
        table.add_column(f"value {i} [unit]", justify="right")
    table.add_row("first", *values)
    table.add_row("second", *reversed(values))
    return table, values


# ------------------------------------------------------------------ the one helper


def test_piped_a_table_is_plain_text_with_every_cell_whole() -> None:
    from reach_driver.cli.tables import show_table

    table, values = _wide_table()
    out = io.StringIO()
    show_table(Console(file=out, width=80), table)  # not a terminal
    text = out.getvalue()
    assert CUT not in text and not BOX.search(text), text
    lines = text.splitlines()
    assert lines[0] == "wide"
    first = lines[2].split()
    assert first == ["first", *values]  # a line per row, every number in full
    assert lines[1].split()[:3] == ["name", "value", "0"]


def test_on_a_narrow_terminal_a_wide_table_is_plain_text_in_blocks_of_its_width() -> None:
    from reach_driver.cli.tables import show_table

    table, values = _wide_table()
    console = Console(file=io.StringIO(), width=80, force_terminal=True, record=True)
    show_table(console, table)
    text = console.export_text()
    assert CUT not in text and not BOX.search(text), text
    assert max(len(line) for line in text.splitlines()) <= 80
    rows = [line.split() for line in text.splitlines() if line.startswith("first")]
    assert len(rows) >= 2  # the columns in blocks, each naming its row
    assert [v for row in rows for v in row[1:]] == values


def test_on_a_terminal_a_table_that_fits_is_drawn() -> None:
    from reach_driver.cli.tables import show_table

    table = Table(title="small")
    table.add_column("joint")
    table.add_column("angle [rad]".replace("[", r"\["), justify="right")
    table.add_row("E", "3.1416")
    console = Console(file=io.StringIO(), width=80, force_terminal=True, record=True)
    show_table(console, table)
    text = console.export_text()
    assert BOX.search(text) and "3.1416" in text and "angle [rad]" in text


def test_plain_text_reads_markup_and_joins_a_cell_of_several_lines() -> None:
    from reach_driver.cli.tables import plain_lines

    table = Table(caption="a [bold]caption[/]")
    table.add_column("device")
    table.add_column("status")
    table.add_row("C (0x03)", "[red]C: ENCODER_FAULT\nD: CAN_BUS_ERROR[/]")
    table.add_section()
    table.add_row("B (0x02)", "ok")
    lines = plain_lines(table)
    assert lines[1] == "C (0x03)  C: ENCODER_FAULT; D: CAN_BUS_ERROR"
    assert set(lines[2]) == {"-"}  # the section break
    assert lines[-1] == "a caption"


def _tables_printed_directly(path: Path) -> list[str]:
    """`something.print(t)` where t is a rich Table (`Table(...)` or a `*_table`/`*_tables`
    builder's call, or a name bound to one): a table printed around `reach_driver.cli.tables`."""
    tree = ast.parse(path.read_text(encoding="utf-8"))

    def builds(value: ast.expr) -> bool:
        return (
            isinstance(value, ast.Call)
            and isinstance(value.func, ast.Name)
            and value.func.id.endswith(("_table", "_tables", "Table"))
        )

    bound = {
        target.id
        for node in ast.walk(tree)
        if isinstance(node, ast.Assign) and builds(node.value)
        for target in node.targets
        if isinstance(target, ast.Name)
    }
    found = []
    for node in ast.walk(tree):
        if not (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "print"
            and node.args
        ):
            continue
        arg = node.args[0]
        if builds(arg) or (isinstance(arg, ast.Name) and arg.id in bound):
            found.append(f"{path}:{node.lineno}")
    return found


def test_every_table_goes_out_through_the_one_helper(tmp_path: Path) -> None:
    files = [f for d in ("reach_driver", "policy", "tools") for f in (ROOT / d).rglob("*.py")]
    printing = [hit for f in files for hit in _tables_printed_directly(f)]
    assert printing == [], "print these with reach_driver.cli.tables.show_table"
    sample = tmp_path / "direct.py"  # and the check sees one
    sample.write_text(
        "t = Table()\nconsole.print(t)\nConsole().print(summary_table(e))\n"
        "s = selection_table(x)\nconsole.print(s)\nconsole.print(text)\n"
    )
    assert len(_tables_printed_directly(sample)) == 3


# ------------------------------------------------------------------ the commands


def _metric_text(value: object) -> str:
    if isinstance(value, bool):
        return "yes" if value else "NO"
    return f"{float(value):.4g}"  # type: ignore[arg-type]


def test_evaluate_piped_prints_every_episodes_metrics_in_full(tmp_path: Path) -> None:
    out = tmp_path / "pid.json"
    tool = [sys.executable, str(ROOT / "tools" / "evaluate.py"), "--controller", "pid"]
    tool += ["--random", "2", "--seconds", "1", "--out", str(out)]
    done = subprocess.run(
        tool, cwd=ROOT, capture_output=True, text=True, timeout=300, env=_env(COLUMNS="80")
    )
    assert done.returncode == 0, done.stderr
    assert CUT not in done.stdout and not BOX.search(done.stdout), done.stdout
    episodes = json.loads(out.read_text())["episodes"]
    rows = {line.split()[0]: line.split() for line in done.stdout.splitlines() if line.strip()}
    header = done.stdout.splitlines()[1]
    for key in ALL_METRIC_KEYS:
        assert metric_label(key) in header, header
    for i, episode in enumerate(episodes):
        cells = rows[str(i)]
        assert cells[1 : 1 + len(ALL_METRIC_KEYS)] == [
            _metric_text(episode["metrics"][k]) for k in ALL_METRIC_KEYS
        ], cells


def _write_recording(path: Path) -> None:
    """A short recorded step response that overshoots and settles."""
    from reach_driver.recording import RunRecorder, StepSample

    target = np.array([2.0, 1.6, 1.0, 0.9])
    start = np.array([1.0, 1.0, 1.5, 0.5])
    with RunRecorder(path, metadata={"controller": "synthetic"}) as rec:
        for k in range(120):
            t = 0.05 * k
            q = target + (start - target) * np.exp(-t / 0.5) * np.cos(3.0 * t)
            rec.log_step(
                StepSample(t=t, step=k, q=q, qdot=np.zeros(4), target=target,
                           current_cmd_mA=np.full(4, 100.0), torque_Nm=np.full(4, 0.3))
            )  # fmt: skip


def test_inspect_on_an_80_column_terminal_shows_every_metric_whole(tmp_path: Path) -> None:
    record = tmp_path / "run.rrd"
    _write_recording(record)
    driver = [sys.executable, "-m", "reach_driver", "inspect", str(record)]
    metrics = json.loads(
        subprocess.run(
            [*driver, "--json"], cwd=ROOT, capture_output=True, text=True, env=_env(), timeout=120
        ).stdout
    )["metrics"]
    code, shown = _on_terminal(driver, columns=80)
    assert code == 0, shown
    assert CUT not in shown, shown
    assert max(len(line) for line in shown.splitlines()) <= 80, shown
    for key, value in metrics.items():
        line = next((x for x in shown.splitlines() if f" {key} " in f"{x} "), None)
        assert line is not None, (key, shown)
        assert metric_label(key) in line and _metric_text(value).lower() in line.lower(), line


def test_run_on_a_120_column_terminal_shows_every_metric_whole(sim) -> None:
    """What `make demo` shows: `reach-driver run` on the terminal it was started from."""
    target = sim.snapshot().q + np.array([0.1, -0.1, 0.1, 0.1])
    run = [sys.executable, "-m", "reach_driver", "--port", str(sim.link)]
    run += ["--watchdog", str(WATCHDOG_S), "-q", "run", "--controller", "pid", "--target"]
    code, shown = _on_terminal([*run, *map(str, target), "--seconds", "1"], columns=120)
    assert "metrics (docs/metrics.md" in shown, shown
    assert CUT not in shown, shown
    assert max(len(line) for line in shown.splitlines()) <= 120, shown
    for key in ALL_METRIC_KEYS:  # a row each: label, a whole number (or yes/no), the key
        assert re.search(
            rf"{re.escape(metric_label(key))}\s*│\s*(yes|no|-?[\d.]+(e[-+]\d+)?)\s*│\s*{key}\b",
            shown,
        ), (key, shown)


def test_monitor_piped_prints_a_plain_line_a_second_as_it_goes(sim) -> None:
    from protocol import DeviceID, HardwareStatus

    sim.inject_fault(int(DeviceID.B), HardwareStatus.JOINT_SERVICE_DUE)
    proc = subprocess.Popen(
        [sys.executable, "-m", "reach_driver", "--port", str(sim.link), "monitor"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        preexec_fn=default_sigint,
    )
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stdout is not None and proc.stderr is not None
    stdout = proc.stdout

    def read() -> None:
        for line in stdout:
            lines.put(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        first = lines.get(timeout=60)  # the first line, while the monitor runs on
        assert proc.poll() is None, "printed only when it exited"
        second = lines.get(timeout=60)
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)
        reader.join(timeout=30)
        err = proc.stderr.read()
    assert code == 0, err
    for line in (first, second):
        assert "nan" not in line.lower(), line
        assert line.startswith("t ") and "| link up |" in line, line
        assert re.search(r"position \[rad, A mm\] E \d\.\d{4} D \d\.\d{4} C \d\.\d{4}", line)
        assert re.search(r"rate \[Hz\] E \d+ D \d+ C \d+ B \d+ A \d+ ", line), line
        assert "| status B C: JOINT_SERVICE_DUE |" in line, line
    assert float(first.split()[1]) < float(second.split()[1])
    rest = []
    while not lines.empty():
        rest.append(lines.get())
    final = "".join(rest)
    assert "E (0x05)" in final and "supply V" in final, final  # the table, at the end
    assert not BOX.search(final) and CUT not in final, final
