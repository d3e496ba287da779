"""Helpers shared by the test modules (import them as `from conftest import ...`) and the
`sim` fixture (a module's own `sim` fixture takes its place there)."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from reach_sim_bridge.emulator.server import SimServer


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimServer]:
    """The virtual arm at 4x real time behind a pty linked at `tmp_path / "arm"`; its loop
    must not have failed by the end of the test. (Imported here, not at the top: the codec's
    tests need no simulator.)"""
    from reach_sim_bridge.emulator.server import SimConfig, SimServer

    server = SimServer(SimConfig(speed=4.0, link=str(tmp_path / "arm")))
    server.start()
    yield server
    server.stop()
    assert server.error is None


def wait_until(
    predicate: Callable[[], object], timeout: float = 5.0, poll_s: float = 0.005
) -> bool:
    """Poll `predicate` until it is truthy or `timeout` seconds pass; its last verdict."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())


def default_sigint() -> None:
    """`preexec_fn` for a child that a test interrupts with SIGINT: Ctrl-C's default action,
    as a shell in the foreground gives it. A non-interactive shell's background jobs (CI run
    with `&`) start with SIGINT ignored, and Python then never raises KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
