"""`reach-driver` as people type it: help that never crashes, options before or after the
command, one exit-code table, a live view while the arm moves, JSON for scripts, labels."""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import LOOPBACK, WATCHDOG_S, default_sigint, wait_until

from protocol import Mode, PacketID
from reach_driver.cli import Exit, main
from reach_driver.cli.parser import build_parser
from reach_driver.metrics import ALL_METRIC_KEYS, METRIC_KEYS
from reach_driver.records import StepRecord

ROOT = Path(__file__).resolve().parents[1]
SPEED = 4.0


pytestmark = pytest.mark.sim(speed=SPEED, udp=LOOPBACK)


def _cli(*argv: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """`python -m reach_driver ARGV` in a child process, as a user runs it."""
    full = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "reach_driver", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env=full,
    )


def _status(argv: list[str]) -> int:
    try:
        return int(main(argv))
    except SystemExit as exc:
        return int(exc.code or 0)


# -- 1: tracebacks and habits --------------------------------------------------------------


@pytest.mark.parametrize(
    "command",
    ["", "info", "monitor", "move", "run", "controllers", "inspect", "export", "workspace"],
)
def test_every_help_prints_without_a_traceback(command, capsys) -> None:
    assert _status([command, "--help"] if command else ["--help"]) == 0
    captured = capsys.readouterr()
    assert "usage: reach-driver" in captured.out
    assert "Traceback" not in captured.err


def test_move_help_shows_its_options_and_the_four_angles(capsys) -> None:
    assert _status(["move", "--help"]) == 0
    out = capsys.readouterr().out
    for text in ("--tolerance", "--timeout", "--jaw", "E D C B", "base angle"):
        assert text in out, out


def test_move_with_too_few_angles_is_a_usage_error_not_a_traceback(capsys) -> None:
    assert _status(["--port", "loop://", "move", "1", "2"]) == Exit.USAGE
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "needs the four angles E D C B (rad), got 2" in err


def test_global_options_work_before_or_after_the_command() -> None:
    parser = build_parser()
    before = parser.parse_args(["--port", "X", "--max-current", "200", "info"])
    after = parser.parse_args(["info", "--port", "X", "--max-current", "200"])
    assert (before.port, before.max_current) == (after.port, after.max_current) == ("X", "200")
    # After the command wins; absent after it leaves the value before it alone.
    both = parser.parse_args(
        ["--port", "A", "run", "--controller", "pid", "--target"]
        + ["3", "1.5", "1.5", "3", "--seconds", "1", "--port", "B", "-q"]
    )
    assert both.port == "B" and both.quiet and both.watchdog == 0.2
    kept = parser.parse_args(["--port", "A", "--watchdog", "0.3", "monitor"])
    assert kept.port == "A" and kept.watchdog == 0.3 and kept.verbose == 0
    # move's own --timeout is the move's; the reply timeout keeps its place before the command.
    move = parser.parse_args(["--timeout", "0.5", "move", "1", "1", "1", "1", "--timeout", "9"])
    assert move.timeout == 0.5 and move.move_timeout == 9.0
    move = parser.parse_args(["move", "1", "1", "1", "1", "--reply-timeout", "0.4"])
    assert move.timeout == 0.4 and move.move_timeout == 60.0


def test_info_takes_the_port_after_the_command(sim, capsys) -> None:
    assert main(["info", "--port", str(sim.link), "--json"]) == Exit.OK
    assert set(json.loads(capsys.readouterr().out)["devices"]) == {"A", "B", "C", "D", "E"}


def test_version_and_python_m() -> None:
    from importlib.metadata import version

    done = _cli("--version")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"reach-driver {version('reach-stack')}"
    help_ = subprocess.run(
        [sys.executable, "-m", "reach_sim_bridge", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert help_.returncode == 0 and "usage: reach-sim" in help_.stdout


def test_log_file_gets_the_command_its_events_and_its_exit(sim, tmp_path, capsys) -> None:
    log = tmp_path / "driver.log"
    assert main(["info", "--port", str(sim.link), "--log-file", str(log), "-q"]) == Exit.OK
    text = log.read_text()
    assert "reach-driver" in text and "info --port" in text and "exit 0" in text
    assert "Traceback" not in capsys.readouterr().err
    code = main(["info", "--port", str(tmp_path / "nope"), "--log-file", str(log)])
    assert code == Exit.NO_ARM
    assert "exit 4" in log.read_text()


def test_an_unwritable_log_file_is_a_usage_error(tmp_path, capsys) -> None:
    code = main(["controllers", "--log-file", str(tmp_path / "no" / "dir" / "x.log")])
    assert code == Exit.USAGE
    assert "--log-file" in capsys.readouterr().err


# -- 2: one exit-code table ----------------------------------------------------------------


def test_help_shows_every_exit_status_once(capsys) -> None:
    assert _status(["--help"]) == 0
    out = capsys.readouterr().out
    table = out.split("exit status (every command):")[1]
    for code in Exit:
        assert re.search(rf"^\s+{int(code)}  \S", table, re.MULTILINE), (code, table)


def _popen(argv: list[str]) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "reach_driver", *argv]
    return subprocess.Popen(
        cmd,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=default_sigint,
    )


def _interrupt(proc: subprocess.Popen[str], ready) -> tuple[str, str]:
    try:
        assert wait_until(ready, timeout=60.0), "the command never got going"
        proc.send_signal(signal.SIGINT)
        return proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()


def test_stopping_monitor_with_ctrl_c_is_a_normal_end(sim) -> None:
    proc = _popen(["--port", str(sim.link), "monitor"])
    heartbeat = sim.firmware._by_id[5]  # the monitor asked the arm to stream
    out, err = _interrupt(proc, lambda: heartbeat.heartbeat_hz > 0)
    assert proc.returncode == Exit.OK, err
    assert "interrupted" not in err and "Traceback" not in err


def test_ctrl_c_during_a_move_stops_the_joints_and_exits_130(sim) -> None:
    target = sim.snapshot().q + np.array([-1.5, 0.0, 0.0, 0.0])  # seconds at the rate limit
    proc = _popen(["--port", str(sim.link), "move", *map(str, target)])
    out, err = _interrupt(proc, lambda: sim.firmware.mode(5) == Mode.POSITION)
    assert proc.returncode == Exit.INTERRUPTED, err
    assert "interrupted: by SIGINT; arm left in zero_velocity (confirmed by the arm)" in err
    # True before it exited: the joints hold where they are instead of going on to the target.
    assert all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in (5, 4, 3, 2))


def test_python_api_advice_is_not_shown_to_an_operator(monkeypatch, capsys) -> None:
    from reach_driver.cli import commands
    from reach_driver.errors import WatchdogTrippedError

    def tripped(args, console):
        raise WatchdogTrippedError(
            "watchdog tripped (no command for 0.21 s); the arm was put in ZERO_VELOCITY; "
            "call rearm() to command again"
        )

    monkeypatch.setitem(commands.COMMANDS, "controllers", tripped)
    assert main(["controllers"]) == Exit.FAILED
    err = capsys.readouterr().err
    assert "rearm()" not in err
    assert "watchdog tripped" in err and "run it again" in err


def test_an_unreachable_arm_is_described_as_it_is_once_the_process_exits() -> None:
    from reach_driver.cli.exits import left_in_for_operator

    # The wording ControlLoop uses when the link is still down at the end of a run.
    loop_says = (
        "unknown: the link is down (read failed) after waiting 3 s; the driver sends "
        "zero_velocity as soon as the arm answers again"
    )
    text = left_in_for_operator(loop_says, "/dev/ttyUSB0")
    assert text.startswith("unknown: the link is down (read failed) after waiting 3 s")
    assert "as soon as the arm answers" not in text
    assert "sends nothing more" in text and "last mode and command" in text
    assert "reach-driver --port /dev/ttyUSB0 info" in text
    assert left_in_for_operator("zero_velocity", "x") == "zero_velocity"


# -- 3: feedback while the arm moves -------------------------------------------------------


def _record(step: int, t: float, wall: float, bad: int = 0) -> StepRecord:
    q = np.array([3.0, 1.5, 1.5, 3.0]) + 0.01 * step
    return StepRecord(
        step=step,
        t=t,
        wall_t=wall,
        q=q,
        qdot=np.zeros(4),
        target=np.array([3.2, 1.6, 1.4, 3.1]),
        raw_command_mA=np.array([100.0, 50.0, -50.0, 10.0]),
        command_mA=np.array([100.0, 50.0, -50.0, 10.0]),
        state_age_s=0.003,
        latency_s=0.001,
        saturated=False,
        barrier=False,
        good_frames=100 + step,
        bad_frames=bad,
        current_mA=np.array([98.0, 49.0, -51.0, 9.0]),
    )


def test_the_live_table_shows_each_joint_and_the_link() -> None:
    from rich.console import Console

    from reach_driver.cli.live import RunView

    view = RunView(Console(file=io.StringIO(), force_terminal=True, width=100), seconds=20)
    assert view.live_mode
    for i in range(21):
        view.on_step(_record(i, i * 0.05, i * 0.05, bad=2))
    shown = Console(record=True, width=100, file=io.StringIO())
    shown.print(view.render())
    text = shown.export_text()
    for column in ("angle [rad]", "target [rad]", "error [rad]", "current [mA]"):
        assert column in text, text
    assert "loop 20.0 Hz" in text and "frames 120 ok, 2 bad" in text
    assert "state age 3.0 ms" in text and "t 1.0 of 20 s" in text
    assert re.search(r"D │\s+1\.7000 │\s+1\.6000 │\s+-0\.1000 │\s+\+49 │\s+\+50", text), text


def test_off_a_terminal_the_view_is_a_line_a_second_and_one_at_the_end() -> None:
    from rich.console import Console

    from reach_driver.cli.live import RunView

    out = io.StringIO()
    view = RunView(Console(file=out, width=100), seconds=20)
    assert not view.live_mode
    with view:
        for i in range(10):  # well within a second
            view.on_step(_record(i, i * 0.05, i * 0.05))
    lines = out.getvalue().splitlines()
    assert len(lines) == 2, lines  # the first step, and where it ended
    assert lines[0].startswith("t   0.0/20 s | error [rad] E +0.200 D +0.100")
    assert "t   0.5/20 s" in lines[1] and "frames 109 ok 0 bad" in lines[1]
    quiet = RunView(Console(file=io.StringIO()), seconds=20, enabled=False)
    with quiet:
        quiet.on_step(_record(0, 0.0, 0.0))
    assert quiet.console.file.getvalue() == ""  # type: ignore[attr-defined]


def test_the_first_progress_line_says_what_is_not_measured_yet_without_nan() -> None:
    from dataclasses import replace

    from rich.console import Console

    from reach_driver.cli.live import RunView

    out = io.StringIO()
    view = RunView(Console(file=out, width=100), seconds=20)
    first = _record(0, 0.0, 0.0)
    view.on_step(replace(first, current_mA=np.array([98.0, np.nan, -51.0, 9.0])))
    line = out.getvalue().splitlines()[0]
    assert "nan" not in line.lower(), line
    assert "loop -- Hz" in line  # one step gives no rate yet
    assert "I [mA] 98 -- -51 9 |" in line  # D's current not read yet


def test_run_shows_progress_while_it_goes_and_still_records(sim, tmp_path, capsys) -> None:
    target = sim.snapshot().q + np.array([0.2, -0.1, 0.1, 0.2])
    record = tmp_path / "run.rrd"
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    argv.append("--target")
    argv += [*map(str, target), "--seconds", "2", "--record", str(record)]
    assert main(argv) == Exit.OK
    captured = capsys.readouterr()
    progress = [line for line in captured.err.splitlines() if line.startswith("t ")]
    assert len(progress) >= 2, captured.err
    assert "error [rad]" in progress[0] and "loop" in progress[-1]
    assert "t   2.0/2 s" in progress[-1] or "t   1.9/2 s" in progress[-1], progress
    assert "| error [rad]" not in captured.out  # stdout keeps the results only
    from reach_driver.rrd_summary import summarize_recording

    summary: dict[str, Any] = summarize_recording(record)
    recorded = summary["recorded_summary"]
    # the recorder's hook ran on every step the loop took (and the state that ended the run);
    # each of the 40 ticks was stepped on, or counted as skipped by a loop a loaded host ran late
    assert summary["steps"] == recorded["steps"] + 1
    assert recorded["steps"] + recorded["skipped_states"] >= 40
    argv[argv.index("--record") : argv.index("--record") + 2] = ["-q"]
    assert main(argv) == Exit.OK
    assert "| error [rad]" not in capsys.readouterr().err


def test_move_prints_the_remaining_error_as_it_goes(sim, capsys) -> None:
    target = sim.snapshot().q + np.array([0.3, -0.2, 0.25, -0.4])
    assert main(["--port", str(sim.link), "move", *map(str, target)]) == Exit.OK
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("move ")]
    assert len(lines) >= 2, err
    assert "error [rad] E +0.300" in lines[0] or "E +0.29" in lines[0], lines
    assert float(lines[-1].rsplit("max |e| ", 1)[1]) <= 0.02


# -- 4: JSON for scripts, tables for people ------------------------------------------------


def test_run_json_is_one_object_with_the_summary_and_metrics(sim, capsys) -> None:
    target = sim.snapshot().q + np.array([0.1, 0.1, -0.1, 0.1])
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    argv.append("--target")
    argv += [*map(str, target), "--seconds", "1", "--json"]
    assert main(argv) == Exit.OK
    out = capsys.readouterr().out
    result = json.loads(out)  # the whole of stdout: one object, nothing else
    assert result["exit"] == 0 and result["ok"] is True
    assert (
        result["controller"] == "pid"
        and result["left_in"] == "zero_velocity (confirmed by the arm)"
    )
    assert result["target"] == pytest.approx(list(target))
    assert set(result["metrics"]) == set(ALL_METRIC_KEYS)
    assert isinstance(result["metrics"]["reached"], bool)
    # 20 ticks in the second, each stepped on or counted as skipped (a loop run late)
    assert result["steps"] + result["skipped_states"] >= 20 and len(result["final_error"]) == 4
    # how the overshoot came about, the same worst joint and value as the metric's
    over = result["overshoot"]
    if result["metrics"]["overshoot_pct"] > 0:
        assert over["pct"] == pytest.approx(result["metrics"]["overshoot_pct"])
        assert over["joint"] in "EDCB" and over["arrival"] == (over["crossing_speed"] >= 0.1)
    else:
        assert over is None


def test_run_says_and_records_what_the_controllers_supervisor_did(sim, tmp_path, capsys) -> None:
    """A controller's `report()` (here ddpg-distilled's settle supervisor) is printed after
    the metrics, is in the JSON, and is kept in the recording's summary."""
    from reach_driver.rrd_summary import summarize_recording

    target = sim.snapshot().q + np.array([0.6, -0.5, 0.5, 0.6])  # far enough to time latency
    record = tmp_path / "settle.rrd"
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "ddpg-distilled"]
    argv += ["--target", *map(str, target), "--seconds", "1.5", "-q"]
    assert main([*argv, "--record", str(record)]) == Exit.OK
    out = capsys.readouterr().out
    assert "controller ddpg-distilled: settle supervisor: loop latency timed at " in out, out
    summary: dict[str, Any] = summarize_recording(record)
    recorded = summary["recorded_summary"]["controller_report"]
    assert recorded["settle"]["latency_periods"] >= 0.0
    assert main([*argv, "--json"]) == Exit.OK
    report = json.loads(capsys.readouterr().out)["controller_report"]
    assert set(report) == {"summary", "settle"}
    assert set(report["settle"]["engaged"]) <= {"E", "D", "C", "B"}
    # without its supervisor the actor has nothing to say
    assert main([*argv, "--param", "settle=0", "--json"]) == Exit.OK
    assert json.loads(capsys.readouterr().out)["controller_report"] == {}


def test_monitor_json_is_one_object_per_line(sim, capsys) -> None:
    argv = ["--port", str(sim.link), "monitor", "--seconds", "1.2", "--json"]
    assert main(argv) == Exit.OK
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) >= 2, lines
    rows = [json.loads(line) for line in lines]
    assert rows[-1]["link"] == "up" and rows[-1]["good_frames"] > 0
    assert set(rows[-1]["devices"]) == {"E", "D", "C", "B", "A"}
    assert rows[-1]["devices"]["E"]["mode"] == "standby"
    assert rows[-1]["devices"]["D"]["rate_hz"] > 0
    assert rows[0]["t"] < rows[-1]["t"]


def test_info_json_has_whole_serial_numbers_and_rounded_floats(sim, capsys) -> None:
    assert main(["--port", str(sim.link), "info", "--json"]) == Exit.OK
    devices = json.loads(capsys.readouterr().out)["devices"]
    d = devices["D"]
    assert d["serial_number"] == 4104 and isinstance(d["serial_number"], int)
    assert isinstance(d["model_number"], int)
    assert d["limits"]["position"] == [0.0175, 3.4034]  # float32 noise rounded away
    assert devices["E"]["limits"]["position"] == [0.0175, 6.143]
    for value in (d["position"], *d["limits"]["velocity"]):
        assert len(repr(value).replace("-", "").replace(".", "").lstrip("0")) <= 6, value


def test_info_fits_80_columns_with_units_on_every_column(sim, capsys) -> None:
    from rich.console import Console

    from reach_driver.cli.render import info_tables
    from reach_driver.cli.tables import show_table
    from reach_driver.client import ArmClient
    from reach_driver.interfaces import open_transport

    with ArmClient(open_transport(str(sim.link))) as client:
        client.request_many(client.found_devices, [PacketID.POSITION], partial=True)
        joints = client.read_info()
    console = Console(record=True, width=80, file=io.StringIO(), force_terminal=True)
    for table in info_tables(str(sim.link), joints):
        show_table(console, table)
    text = console.export_text()
    assert "┃" in text  # drawn as tables: each fits a terminal of 80 columns
    assert max(len(line) for line in text.splitlines()) <= 80
    cells: tuple[str, ...] = (
        "E (0x05)",
        "0.0175 .. 6.143 rad",
        "0.0175 .. 3.4034 rad",
        "0 .. 6.28319 rad",
    )
    cells += ("±0.5236 rad/s", "±600 mA", "±3 mm/s", "5.0000 mm", "0.1.0", "4104", "ok")
    for cell in cells:
        assert cell in text, text  # each on one line, not broken over two
    # and through the CLI at 80 columns
    done = _cli("--port", str(sim.link), "info", env={"COLUMNS": "80"})
    assert done.returncode == 0, done.stderr
    assert max(len(line) for line in done.stdout.splitlines()) <= 80, done.stdout


# -- 5: one name and unit per metric -------------------------------------------------------

LABELS = (
    "energy [J]",
    "RMSE [rad]",
    "MIE [rad s]",
    "MSSE [rad]",
    "overshoot [%]",
    "settling time [s]",
    "reached",
)


def test_every_metric_has_one_label_with_its_unit() -> None:
    from reach_driver.metrics import METRIC_LABELS, metric_label

    assert set(METRIC_LABELS) >= set(ALL_METRIC_KEYS)
    assert tuple(metric_label(k) for k in METRIC_KEYS) == LABELS
    assert metric_label("at_rest_new_key") == "at_rest_new_key"  # unlabelled: shown by key


def test_run_and_inspect_label_the_metrics_the_same_way(tmp_path) -> None:
    from rich.console import Console

    from reach_driver.cli.render import metrics_table, print_recording

    values = {
        "energy_j": 1.2,
        "rmse": 0.1,
        "mie": 0.3,
        "msse": 0.001,
        "overshoot_pct": 2.0,
        "settling_time_s": 3.5,
        "reached": True,
    }
    run = Console(record=True, width=200, file=io.StringIO())
    run.print(metrics_table("metrics", values))
    ins = Console(record=True, width=200, file=io.StringIO())
    summary = {"file": "x.rrd", "steps": 2, "duration_s": 1.0, "joints": list("EDCB")}
    summary |= {k: [0.0] * 4 for k in ("final_target", "final_position", "final_error")}
    print_recording(ins, {**summary, "metrics": values})
    for text in (run.export_text(), ins.export_text()):
        for label in LABELS:
            assert label in text, text


def test_an_unknown_controller_is_a_bad_command_line_in_every_tool(capsys) -> None:
    """Exit 2 from reach-driver run and from tools/evaluate.py alike (one exit-code table)."""
    argv = ["--port", "/nonexistent", "run", "--controller", "nope", "--seconds", "1"]
    assert main([*argv, "--target", "1", "1", "1", "1"]) == Exit.USAGE
    assert "unknown controller 'nope'" in capsys.readouterr().err
    tool = Path(__file__).resolve().parents[1] / "tools" / "evaluate.py"
    proc = subprocess.run(
        [sys.executable, str(tool), "--controller", "nope", "--random", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
