"""The CLI attacked: the link lost mid-command, hostile options, floods of fault events.

Each test here failed on the code before its fix (see the commit that added it)."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from conftest import LOOPBACK, wait_until

from protocol import Mode
from reach_driver.cli import Exit, main

pytestmark = pytest.mark.sim(speed=1.0, udp=LOOPBACK)


def _in_thread(argv: list[str]) -> tuple[threading.Thread, dict[str, object]]:
    """main(argv) on a thread; its exit status and when it returned go into the dict."""
    result: dict[str, object] = {}

    def target() -> None:
        result["code"] = main(argv)
        result["ended"] = time.monotonic()

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread, result


# -- 1: the link lost mid-command ----------------------------------------------------------


def test_move_stops_at_once_when_the_link_is_lost_and_says_why(sim, capsys) -> None:
    q0 = sim.snapshot().q
    target = q0 + np.array([-1.5, 0.0, 0.0, 0.0])  # seconds of arm time at the rate limit
    thread, result = _in_thread(["--port", str(sim.link), "move", *map(str, target)])
    assert wait_until(lambda: sim.firmware.mode(5) == Mode.POSITION, timeout=20.0)
    assert sim.wait_sim_time(sim.sim_time + 0.2, timeout=20)  # 0.2 s into a 3 s move
    sim.stop()  # an outage: the pty goes away, the firmware keeps its state
    lost_at = time.monotonic()
    thread.join(timeout=30.0)  # the move's --timeout is the default 60 s
    assert not thread.is_alive(), "move still polling stale state after the link was lost"
    err = capsys.readouterr().err
    assert result["code"] == Exit.LINK_LOST, err
    # It stopped on the link loss, not on a timeout (stale_link_s is 1 s; 60 s is the timeout).
    assert float(result["ended"]) - lost_at < 10.0  # type: ignore[arg-type]
    assert "timed out" not in err
    assert "link lost during the move" in err
    assert re.search(r"down for \d+\.\d+ s", err), err
    assert "last known positions (rad)" in err
    for letter in "EDCB":
        assert re.search(rf"{letter} \d\.\d{{4}}", err), err


def test_run_stops_when_the_link_is_lost(sim, capsys) -> None:
    target = sim.snapshot().q + np.array([0.2, 0.2, 0.2, 0.2])
    argv = ["--port", str(sim.link), "run", "--controller", "pid", "--target"]
    argv += [*map(str, target), "--seconds", "600"]
    thread, result = _in_thread(argv)
    assert wait_until(lambda: sim.firmware.mode(5) == Mode.CURRENT, timeout=20.0)
    assert sim.wait_sim_time(sim.sim_time + 0.5, timeout=20)  # ten control steps in
    sim.stop()
    thread.join(timeout=30.0)
    assert not thread.is_alive(), "run went on after the link was lost"
    captured = capsys.readouterr()
    assert result["code"] == Exit.FAILED, captured.err
    assert "run failed" in captured.out
    # Either the next command found the link down or the feedback stopped: both say so.
    assert re.search(r"link (down|is down)|feedback stopped", captured.out), captured.out
    assert "arm left in unknown" in captured.out
    # The process exits right after: it cannot promise to send anything later.
    assert "as soon as the arm answers" not in captured.out
    assert "sends nothing more" in captured.out


# -- 4: hostile options, markup in messages, floods of fault events ------------------------


def _exit_status(argv: list[str]) -> int:
    """main's exit status, parse errors included; any other exception (a traceback) fails."""
    try:
        return int(main(argv))
    except SystemExit as exc:
        return int(exc.code or 0)


def _run() -> list[str]:
    return ["run", "--controller", "pid", "--target", "3", "1.5", "1.5", "3", "--seconds", "1"]


HOSTILE = {
    "monitor --rate 0": (["monitor", "--rate", "0", "--seconds", "0.3"], "1..255 Hz"),
    "monitor --rate 300": (["monitor", "--rate", "300", "--seconds", "0.3"], "1..255 Hz"),
    "run --period 0.0001": ([*_run(), "--period", "0.0001"], "at least 0.001 s"),
    "run --period 0.002 (stream)": ([*_run(), "--period", "0.002"], "1/255 s"),
    "run --param kp=nan": ([*_run(), "--param", "kp=nan"], "finite"),
    "run --param kp=1,inf": ([*_run(), "--param", "kp=1,inf,1,1"], "finite"),
    "run --param weights=missing.npz": (
        ["run", "--controller", "ddpg-distilled", "--target", "3", "1.5", "1.5", "3"]
        + ["--seconds", "1", "--param", "weights=missing.npz"],
        "missing.npz",
    ),
    "--retries -5": (["--retries", "-5", "info"], "must be >= 0"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_hostile_options_get_one_clear_line_and_a_usage_exit(sim, case, capsys) -> None:
    argv, expected = HOSTILE[case]
    code = _exit_status(["--port", str(sim.link), *argv])
    err = capsys.readouterr().err
    assert code == Exit.USAGE, err
    assert expected in err, err
    assert "Traceback" not in err
    assert "no arm" not in err


def test_arm_and_user_text_is_not_taken_for_markup(monkeypatch, capsys) -> None:
    from reach_driver.cli import commands
    from reach_driver.errors import DriverError

    def explode(args, console):
        raise DriverError("controller returned [nan, nan, nan, nan]: need 4 finite currents")

    monkeypatch.setitem(commands.COMMANDS, "controllers", explode)
    assert main(["controllers"]) == Exit.FAILED
    assert "[nan, nan, nan, nan]" in capsys.readouterr().err


def test_repeated_fault_events_are_rate_limited_with_a_count() -> None:
    from rich.console import Console

    from reach_driver.cli.connect import EventPrinter
    from reach_driver.link import ClientEvent, EventKind

    now = [0.0]
    console = Console(record=True, width=200, force_terminal=False)
    printer = EventPrinter(console, clock=lambda: now[0])
    fault = ClientEvent(EventKind.FAULT, 0.0, "D (0x04) reports [MOTOR_OVER_TEMP]", 4)
    clear = ClientEvent(EventKind.FAULT_CLEARED, 0.0, "D (0x04) status clear", 4)
    other = ClientEvent(EventKind.FAULT, 0.0, "C (0x03) reports ENCODER_ERROR", 3)
    for _ in range(900):  # a flag toggling: 1,800 events in 0.9 s
        printer(fault)
        printer(clear)
        now[0] += 0.001
    printer(other)  # another device is not held back by D's flood
    now[0] = 1.5
    printer(fault)
    lines = console.export_text().splitlines()
    assert len(lines) == 4, lines
    assert lines[0] == "fault: D (0x04) reports [MOTOR_OVER_TEMP]"  # and not eaten as markup
    assert lines[1] == "fault cleared: D (0x04) status clear"
    assert lines[2] == "fault: C (0x03) reports ENCODER_ERROR"
    assert "899 more like this" in lines[3] and "MOTOR_OVER_TEMP" in lines[3]
