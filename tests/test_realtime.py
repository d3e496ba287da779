"""`run --realtime`: the threads a command waits on (the control loop, the link's reader) ask
for SCHED_FIFO; `try` goes on without it and says why, `require` refuses the run before anything
is commanded, `off` never asks; a trip on a busy machine names a missing real-time priority
(docs/reliability.md 46-2, docs/hil.md)."""

from __future__ import annotations

import json
import os
import re
import threading
from typing import Any

import numpy as np
import pytest
from conftest import LOOPBACK, WATCHDOG_S, udp_url

from protocol import PacketID, commands
from reach_driver import ArmClient, ControlLoop, RealtimeRefusedError, open_transport, recording
from reach_driver import realtime as rt
from reach_driver.cli import Exit, main
from reach_driver.cli.live import RunView
from reach_driver.cli.recorder import WRITER_THREAD
from reach_driver.loop_timing import GapLog
from reach_driver.realtime import (
    RealtimePolicy,
    RealtimeStatus,
    RealtimeThreads,
    ThreadRole,
)
from reach_driver.rrd_summary import read_recording
from reach_driver.watchdog import LoopTiming, Watchdog

pytestmark = pytest.mark.sim(speed=4.0, udp=LOOPBACK)

E = 0x05
RESET = int(getattr(os, "SCHED_RESET_ON_FORK", 0))
READER_PREFIX = "reach-driver reader"


class Zero:
    """A controller that asks for no current (the runs are about scheduling, not motion)."""

    def reset(self) -> None:
        pass

    def act(self, state, target) -> np.ndarray:  # noqa: ANN001
        return np.zeros(4)


def _refuse(monkeypatch: pytest.MonkeyPatch, *, has_sys_nice: bool = False) -> list[int]:
    """os.sched_setscheduler raises PermissionError (as for a user without CAP_SYS_NICE or
    an rtprio limit); returns the list of the policies it was asked for."""
    asked: list[int] = []

    def refuse(pid: int, policy: int, param: Any) -> None:
        asked.append(policy)
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(rt, "_has_sys_nice", lambda: has_sys_nice)
    return asked


def _never_asked(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    asked: list[int] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, policy, param: asked.append(policy))
    return asked


def _commands_received(sim, monkeypatch: pytest.MonkeyPatch) -> list[int]:  # noqa: ANN001
    """The packet ids the virtual arm is sent from now on."""
    got: list[int] = []
    handle = sim.firmware.handle

    def spy(packet):  # noqa: ANN001, ANN202
        got.append(int(packet.packet_id))
        return handle(packet)

    monkeypatch.setattr(sim.firmware, "handle", spy)
    return got


def _run_argv(sim, *extra: str) -> list[str]:  # noqa: ANN001
    target = sim.snapshot().q + np.array([0.1, -0.1, 0.1, 0.1])
    argv = ["--port", udp_url(sim), "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    return argv + ["--target", *map(str, target), "--seconds", "1", *extra]


def _permitted() -> bool:
    """Whether this machine gives a thread SCHED_FIFO (asked in a thread that then ends)."""
    got: list[bool] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | RESET, os.sched_param(rt.DEFAULT_PRIORITY))
            got.append(True)
        except (AttributeError, OSError):
            got.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return got[0]


def _policy(tid: int = 0) -> tuple[int, int]:
    return os.sched_getscheduler(tid) & ~RESET, os.sched_getparam(tid).sched_priority


# -- the policy, with the kernel refusing -----------------------------------------------------


def test_a_refusal_is_typed_and_says_what_grants_it(monkeypatch) -> None:
    _refuse(monkeypatch)
    got = RealtimeThreads(RealtimePolicy.TRY).enter(ThreadRole.LOOP)
    assert got.status is RealtimeStatus.NOT_PERMITTED and not got.granted
    assert "needs CAP_SYS_NICE or an rtprio limit of at least 10" in got.reason
    assert "`ulimit -r` is " in got.reason
    # A process that has CAP_SYS_NICE and is still refused: its control group is why.
    monkeypatch.setattr(rt, "_has_sys_nice", lambda: True)
    got = RealtimeThreads(RealtimePolicy.TRY).enter(ThreadRole.LOOP)
    assert "cpu.rt_runtime_us" in got.reason


def test_not_supported_where_the_os_has_no_real_time_scheduling(monkeypatch) -> None:
    monkeypatch.delattr(os, "sched_setscheduler")
    got = RealtimeThreads(RealtimePolicy.REQUIRE).enter(ThreadRole.READER)
    assert got.status is RealtimeStatus.NOT_SUPPORTED


def test_try_goes_on_without_it_and_the_summary_says_why(sim, monkeypatch) -> None:
    asked = _refuse(monkeypatch)
    client = ArmClient(open_transport(udp_url(sim)))
    client.realtime = RealtimeThreads(RealtimePolicy.TRY)
    with client.start():
        summary = ControlLoop(client, Zero(), 0.05).run(client.read_joints().q, 0.5)
    assert summary.ok, summary.error
    assert summary.steps > 0
    report = summary.timing.realtime
    assert not report.granted and report.refusal() is None
    assert [o.role for o in report.outcomes] == [ThreadRole.LOOP, ThreadRole.READER]
    assert report.describe().startswith(
        "without real-time priority: not permitted for the control loop and the link reader: "
        "needs CAP_SYS_NICE"
    )
    assert len(asked) == 2  # each thread asked once, for itself


def test_try_says_it_once_in_the_output_and_in_json(sim, monkeypatch, capsys) -> None:
    _refuse(monkeypatch)
    assert main(_run_argv(sim, "-q")) == Exit.OK
    out, err = capsys.readouterr()
    flat = " ".join((out + err).split())  # the console wraps long lines
    assert flat.count("without real-time priority") == 1, out + err
    # beside the loop period's figures
    assert re.search(r"loop period p50 [^;]* gaps; without real-time priority: not perm", flat)
    assert main(_run_argv(sim, "-q", "--json")) == Exit.OK
    out, _ = capsys.readouterr()
    got = json.loads(out)["realtime"]
    assert got["policy"] == "try" and got["granted"] is False
    assert got["without"].startswith("not permitted for the control loop and the link reader")
    assert got["threads"]["control loop"]["status"] == "not permitted"


def test_require_refuses_the_run_before_any_command(sim, monkeypatch, capsys, tmp_path) -> None:
    _refuse(monkeypatch)
    received = _commands_received(sim, monkeypatch)
    record = tmp_path / "run.rrd"
    code = main(_run_argv(sim, "--realtime", "require", "--record", str(record)))
    out, err = capsys.readouterr()
    assert code == Exit.NO_REALTIME == 7, out + err
    lines = err.strip().splitlines()
    assert lines == [
        "refused: real-time priority required but not permitted for the link reader: needs "
        f"CAP_SYS_NICE or an rtprio limit of at least 10 (`ulimit -r` is {rt._rtprio_limit()}); "
        "nothing was commanded"
    ], err
    assert "Traceback" not in out + err
    # Only requests (discovery, identity, limits) reached the arm; no recording was opened.
    assert received and set(received) == {PacketID.REQUEST}
    assert not record.exists()


def test_require_in_the_api_raises_before_any_command(sim, monkeypatch) -> None:
    _refuse(monkeypatch)
    client = ArmClient(open_transport(udp_url(sim)))
    client.realtime = RealtimeThreads(RealtimePolicy.REQUIRE)
    with client.start():
        q = client.read_joints().q
        received = _commands_received(sim, monkeypatch)
        with pytest.raises(RealtimeRefusedError, match="nothing was commanded"):
            ControlLoop(client, Zero(), 0.05).run(q, 0.5)
    assert PacketID.CURRENT not in received and PacketID.MODE not in received


def test_off_never_asks(sim, monkeypatch, capsys) -> None:
    asked = _never_asked(monkeypatch)
    assert main(_run_argv(sim, "-q", "--json", "--realtime", "off")) == Exit.OK
    out, _ = capsys.readouterr()
    got = json.loads(out)["realtime"]
    assert asked == []
    assert got["policy"] == "off" and got["without"] is None
    assert {t["status"] for t in got["threads"].values()} == {"not asked"}


def test_other_commands_never_ask(sim, monkeypatch, capsys) -> None:
    asked = _never_asked(monkeypatch)
    assert main(["--port", udp_url(sim), "info", "--json"]) == Exit.OK
    capsys.readouterr()
    assert asked == []


# -- granted: the loop really runs SCHED_FIFO -------------------------------------------------


def test_the_loop_and_reader_run_sched_fifo_and_the_recorder_does_not(
    sim, monkeypatch, capsys, tmp_path
) -> None:
    if not _permitted():
        pytest.skip("this machine gives no SCHED_FIFO (needs CAP_SYS_NICE or `ulimit -r`)")
    seen: dict[str, set[tuple[int, int]]] = {"loop": set(), "reader": set(), "writer": set()}
    on_step = RunView.on_step

    def loop_spy(self, record) -> None:  # noqa: ANN001
        seen["loop"].add(_policy())
        for t in threading.enumerate():
            if t.name.startswith(READER_PREFIX) and t.native_id is not None:
                seen["reader"].add(_policy(t.native_id))
        on_step(self, record)

    class Spy(recording.RunRecorder):
        def log_step(self, s: recording.StepSample) -> None:
            if threading.current_thread().name == WRITER_THREAD:  # the last: the caller's
                seen["writer"].add(_policy())
            super().log_step(s)

    monkeypatch.setattr(RunView, "on_step", loop_spy)
    monkeypatch.setattr(recording, "RunRecorder", Spy)
    before = _policy()
    code = main(_run_argv(sim, "-q", "--json", "--record", str(tmp_path / "run.rrd")))
    out, err = capsys.readouterr()
    assert code == Exit.OK, out + err
    fifo = (os.SCHED_FIFO, rt.DEFAULT_PRIORITY)
    assert seen["loop"] == {fifo} and seen["reader"] == {fifo}
    # The recorder's writer, started by the loop's thread, stays ordinary (RESET_ON_FORK).
    assert seen["writer"] == {(os.SCHED_OTHER, 0)}
    assert _policy() == before  # the caller's thread has its own scheduling back
    got = json.loads(out)["realtime"]
    assert got["granted"] is True and got["without"] is None
    assert got["threads"]["control loop"] == {"status": "granted", "priority": 10, "reason": ""}
    assert read_recording(tmp_path / "run.rrd").summary["realtime"] == got  # the recording too


def test_a_thread_already_real_time_above_it_keeps_its_own() -> None:
    if not _permitted():
        pytest.skip("this machine gives no SCHED_FIFO (needs CAP_SYS_NICE or `ulimit -r`)")
    got: list[Any] = []

    def chrt_20() -> None:  # as under `chrt -f 20 reach-driver ...`
        os.sched_setscheduler(0, os.SCHED_FIFO | RESET, os.sched_param(20))
        with RealtimeThreads(RealtimePolicy.REQUIRE).held(ThreadRole.LOOP) as outcome:
            got.append((outcome, _policy()))
        got.append(_policy())

    t = threading.Thread(target=chrt_20)
    t.start()
    t.join()
    (outcome, during), after = got
    assert outcome.granted and outcome.priority == 20
    assert during == after == (os.SCHED_FIFO, 20)


# -- the watchdog's message -------------------------------------------------------------------

WHY = "not permitted for the control loop and the link reader: needs CAP_SYS_NICE"


def _armed_watchdog() -> Watchdog:
    w = Watchdog()
    w.note_sent([commands.current(E, 100.0)], 0.0)
    return w


def test_a_busy_machine_trip_without_real_time_says_it_was_not_granted() -> None:
    busy = LoopTiming(0.05, 0.120, 0.180, 200, without_realtime=WHY)
    reason, _ = _armed_watchdog().expired(0.289, 0.2, lambda dev: 0.28, loop=busy)  # type: ignore[misc]
    assert (
        "the machine was busy (loop period p99 120.0 ms, max 180.0 ms over 200 periods of 50 ms); "
        f"real-time priority was not granted: {WHY}; raise" in reason
    )
    # The whole process not run, before the loop's second command: said all the same.
    early = GapLog().timing(0.05, WHY)
    assert early is not None and early.gaps == 0
    reason, _ = _armed_watchdog().expired(0.3, 0.2, lambda dev: 0.29, away_s=0.25, loop=early)  # type: ignore[misc]
    assert f"the machine was busy; real-time priority was not granted: {WHY}; raise" in reason
    assert "nan" not in reason
    reason, _ = _armed_watchdog().expired(0.3, 0.2, lambda dev: 0.05, away_s=0.25, loop=early)  # type: ignore[misc]
    assert f"(the machine was busy; real-time priority was not granted: {WHY}; raise" in reason


def test_a_trip_with_real_time_granted_or_a_slow_controller_does_not_mention_it() -> None:
    granted = LoopTiming(0.05, 0.120, 0.180, 200)
    reason, _ = _armed_watchdog().expired(0.289, 0.2, lambda dev: 0.28, loop=granted)  # type: ignore[misc]
    assert "the machine was busy" in reason and "real-time" not in reason
    calm = LoopTiming(0.05, 0.051, 0.052, 200, without_realtime=WHY)
    reason, _ = _armed_watchdog().expired(0.3, 0.2, lambda dev: 0.29, loop=calm)  # type: ignore[misc]
    assert "the controller did not command" in reason and "real-time" not in reason
    assert GapLog().timing(0.05) is None
