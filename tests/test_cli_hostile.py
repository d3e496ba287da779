"""The CLI attacked: the link lost mid-command, hostile options, floods of fault events.

Each test here failed on the code before its fix (see the commit that added it)."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from conftest import wait_until

from protocol import Mode
from reach_driver.cli import Exit, main
from reach_sim_bridge.server import SimConfig, SimServer


@pytest.fixture
def sim(tmp_path):
    server = SimServer(SimConfig(speed=1.0, link=str(tmp_path / "arm"), udp=("127.0.0.1", 0)))
    server.start()
    yield server
    server.stop()
    assert server.error is None


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
    time.sleep(0.2)
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
    time.sleep(0.5)
    sim.stop()
    thread.join(timeout=30.0)
    assert not thread.is_alive(), "run went on after the link was lost"
    captured = capsys.readouterr()
    assert result["code"] == Exit.FAILED, captured.err
    assert "run failed" in captured.out
    # Either the next command found the link down or the feedback stopped: both say so.
    assert re.search(r"link (down|is down)|feedback stopped", captured.out), captured.out
    assert "arm left in unknown" in captured.out
