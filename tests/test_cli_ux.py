"""`reach-driver` as people type it: help that never crashes, options before or after the
command, one exit-code table, a live view while the arm moves, JSON for scripts, labels."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import wait_until

from protocol import Mode
from reach_driver.cli import Exit, main
from reach_driver.cli.parser import build_parser
from reach_sim_bridge.server import SimConfig, SimServer

ROOT = Path(__file__).resolve().parents[1]
SPEED = 4.0


@pytest.fixture
def sim(tmp_path):
    server = SimServer(SimConfig(speed=SPEED, link=str(tmp_path / "arm"), udp=("127.0.0.1", 0)))
    server.start()
    yield server
    server.stop()
    assert server.error is None


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
    "command", ["", "info", "monitor", "move", "run", "controllers", "inspect"]
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
    assert "required: C, B" in err


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
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
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
    assert "arm left in a safe mode" in err
    # True: the joints hold where they are instead of going on to the target.
    assert wait_until(
        lambda: all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in (5, 4, 3, 2)), timeout=10.0
    )


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
