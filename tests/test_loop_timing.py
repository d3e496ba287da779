"""The loop keeps time on a busy machine: what would hold a command up is kept off the loop's
thread, each gap between commands is taken apart (GC included), and a watchdog trip says when
the machine, not the controller, was the cause and names the option to raise."""

from __future__ import annotations

import gc
import threading

import numpy as np
import pytest
from conftest import LOOPBACK, WATCHDOG_S, udp_url

from protocol import commands
from reach_driver import ArmClient, ControlLoop, StepRecord, open_transport, recording
from reach_driver.cli import Exit, main
from reach_driver.cli.exits import for_operator
from reach_driver.cli.recorder import WRITER_THREAD
from reach_driver.loop_timing import GapLog
from reach_driver.rrd_summary import read_recording
from reach_driver.watchdog import LIMIT_NAME, LoopTiming, Watchdog

pytestmark = pytest.mark.sim(speed=4.0, udp=LOOPBACK)

E = 0x05


class Zero:
    """A controller that asks for no current (the run is about timing, not motion)."""

    def reset(self) -> None:
        pass

    def act(self, state, target) -> np.ndarray:  # noqa: ANN001
        return np.zeros(4)


def _cyclic_garbage(n: int = 20_000) -> None:
    """Objects only the cycle collector frees."""
    for _ in range(n):
        a: list[object] = []
        a.append(a)


# -- the recorder is off the loop's thread ---------------------------------------------------


def test_run_logs_its_steps_on_the_recorders_thread_not_the_loops(
    sim, tmp_path, monkeypatch, capsys
) -> None:
    logged: list[tuple[int, str]] = []

    class Spy(recording.RunRecorder):
        def log_step(self, s: recording.StepSample) -> None:
            logged.append((s.step, threading.current_thread().name))
            super().log_step(s)

    monkeypatch.setattr(recording, "RunRecorder", Spy)
    record = tmp_path / "run.rrd"
    target = sim.snapshot().q + np.array([0.2, -0.1, 0.1, 0.2])
    argv = ["--port", udp_url(sim), "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    argv += ["--target", *map(str, target), "--seconds", "1", "--record", str(record), "-q"]
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == Exit.OK, out + err
    # The loop runs on this (the main) thread; every step it took was logged on the writer's.
    # The state that ended the run is logged by `finish`, after the loop, on the caller's.
    *during, (last_step, _) = sorted(logged)
    assert during and {name for _, name in during} == {WRITER_THREAD}
    assert all(step < last_step for step, _ in during)
    # ...and the file holds every step, the loop period of each but the first included.
    run = read_recording(record)
    assert len(run.step) == len(logged)
    assert run.loop_period_ms is not None
    assert np.isnan(run.loop_period_ms[0]) and np.all(run.loop_period_ms[1:-1] > 0)


# -- each gap taken apart ----------------------------------------------------------------------


def test_a_gc_pause_inside_a_gap_is_attributed_to_it() -> None:
    log = GapLog()
    log.start()
    try:
        log.command(1.0, 0, 0.0)
        _cyclic_garbage()
        gc.collect()
        log.command(1.2, 1, 0.05)
        log.command(1.25, 2, 0.10)  # a gap with no collection
    finally:
        log.stop()
    stats = log.stats()
    assert stats.count == 2 and stats.gc_pauses >= 1 and stats.gc_total_s > 0
    by_step = {g.step: g for g in stats.longest}
    assert by_step[1].gc_s > 0 and by_step[2].gc_s == 0
    assert "garbage collection" in by_step[1].describe()
    # Registered for the run only.
    assert all(cb is not log.pauses for cb in gc.callbacks)


def test_the_summary_counts_gc_pauses_and_the_loop_period(sim_factory) -> None:
    server = sim_factory(speed=4.0, pty=False, udp=LOOPBACK)
    with ArmClient(open_transport(udp_url(server))) as client:

        def hook(r: StepRecord) -> None:
            if r.step == 5:  # a collection in the middle of the run, after a command
                _cyclic_garbage()
                gc.collect()

        loop = ControlLoop(client, Zero(), 0.05, on_step=hook)
        summary = loop.run(client.read_joints().q, 1.0)
    gaps = summary.timing.gaps
    assert summary.ok, summary.error
    assert gaps.gc_pauses >= 1
    assert gaps.count == summary.steps - 1
    assert gaps.p50_s <= gaps.p99_s <= gaps.p999_s <= gaps.max_s
    assert gaps.longest and all(g.gap_s > 0 for g in gaps.longest)
    assert client.loop_timing is None  # the watchdog's view of the loop ends with it


# -- the watchdog says what happened and names the option --------------------------------------


def _armed_watchdog(now: float) -> Watchdog:
    w = Watchdog()
    w.note_sent([commands.current(E, 100.0)], now)
    return w


def test_a_trip_on_a_busy_machine_says_so_and_names_the_watchdog_option() -> None:
    w = _armed_watchdog(0.0)
    busy = LoopTiming(nominal_s=0.05, p99_s=0.120, max_s=0.180, gaps=200)
    got = w.expired(0.289, 0.2, lambda dev: 0.28, loop=busy)
    assert got is not None
    reason, devices = got
    assert devices == (E,)
    assert reason.startswith("no command for 0.289 s")
    assert "the controller did not command for 0.289 s: the machine was busy" in reason
    assert "loop period p99 120.0 ms" in reason
    assert f"raise {LIMIT_NAME} or reduce the load" in reason
    assert "raise --watchdog or reduce the load" in for_operator(reason)


def test_a_trip_after_this_process_did_not_run_does_not_blame_the_controller() -> None:
    w = _armed_watchdog(0.0)
    # The reader itself was away 0.25 s: the feedback it just read is fresh, the loop had no
    # chance to command.
    reason, _ = w.expired(0.289, 0.2, lambda dev: 0.288, away_s=0.25)  # type: ignore[misc]
    assert "this process did not run for 0.250 s" in reason
    assert "the machine was busy" in reason and "the controller did not command" not in reason
    assert "raise --watchdog or reduce the load" in for_operator(reason)


def test_a_trip_with_the_loop_on_time_still_blames_the_controller() -> None:
    w = _armed_watchdog(0.0)
    calm = LoopTiming(nominal_s=0.05, p99_s=0.051, max_s=0.052, gaps=200)
    reason, _ = w.expired(0.3, 0.2, lambda dev: 0.29, loop=calm)  # type: ignore[misc]
    assert "feedback kept arriving: the controller did not command" in reason
    assert "the machine was busy" not in reason and "p99 51.0 ms" in reason
