"""Every way a move or run ends takes one path: the arm put in its safe mode and that
confirmed by the arm (or said not to be), the summary printed, the recording closed, the
documented exit status. Each test here failed on the code before its fix (docs/reliability.md,
"Holes found": the exit paths)."""

from __future__ import annotations

import json
import re
import signal
from pathlib import Path

import numpy as np
import pytest
from conftest import LOOPBACK, WATCHDOG_S, udp_url, wait_until

from policy.campaigns.attacks import (
    HangingLink,
    driver_process,
    finish_process,
    lie_about_velocity,
)
from protocol import Mode
from reach_driver import ArmClient, ControlLoop, ControlState, Interrupted, open_transport
from reach_driver.cli import Exit, main
from reach_driver.rrd_summary import read_recording

ROOT = Path(__file__).resolve().parents[1]
JOINT_IDS = (5, 4, 3, 2)

pytestmark = pytest.mark.sim(speed=1.0, udp=LOOPBACK)


def _modes(sim) -> list[Mode]:
    return [sim.firmware.mode(d) for d in JOINT_IDS]


def _run_argv(port: str, sim, *extra: str) -> list[str]:
    # E pushed 1.5 rad away: the PID saturates it at its 600 mA limit for seconds.
    target = sim.snapshot().q + np.array([1.5, 0.2, 0.2, 0.2])
    target[0] = min(target[0], 6.0)
    argv = ["--port", port, "--watchdog", str(WATCHDOG_S), *extra, "run"]
    return argv + ["--controller", "pid", "--target", *map(str, target), "--seconds", "600"]


# -- 1: SIGHUP, SIGQUIT, SIGTERM and SIGINT end a run and a move one way -----------------------


@pytest.mark.parametrize(
    "sig", [signal.SIGHUP, signal.SIGQUIT, signal.SIGTERM, signal.SIGINT], ids=lambda s: s.name
)
def test_every_signal_ends_a_run_with_the_arm_safe_the_summary_and_the_recording(
    sim, tmp_path, sig
) -> None:
    record = tmp_path / "run.rrd"
    proc = driver_process(*_run_argv(str(sim.link), sim), "--record", str(record))
    try:
        assert wait_until(lambda: sim.firmware.mode(5) == Mode.CURRENT, timeout=60.0), (
            "the run never commanded the arm"
        )
        proc.send_signal(sig)
    finally:
        out, err = finish_process(proc)
    # Confirmed by the arm before the process exited: no waiting here.
    assert _modes(sim) == [Mode.ZERO_VELOCITY] * 4, (out, err)
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err
    assert "steps" in out  # the summary table
    assert "arm left in zero_velocity (confirmed by the arm)" in out
    assert f"interrupted: by {sig.name}; arm left in zero_velocity (confirmed by the arm)" in err
    recorded = read_recording(record).summary
    assert recorded["left_in"] == "zero_velocity (confirmed by the arm)"
    assert f"interrupted by {sig.name}" in str(recorded["stopped_by"])


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGQUIT], ids=lambda s: s.name)
def test_a_signal_stops_a_move_where_it_is(sim, sig) -> None:
    target = sim.snapshot().q + np.array([-1.5, 0.0, 0.0, 0.0])  # seconds at the rate limit
    proc = driver_process("--port", str(sim.link), "move", *map(str, target))
    try:
        assert wait_until(lambda: sim.firmware.mode(5) == Mode.POSITION, timeout=60.0)
        proc.send_signal(sig)
    finally:
        out, err = finish_process(proc)
    assert _modes(sim) == [Mode.ZERO_VELOCITY] * 4, (out, err)
    assert proc.returncode == 128 + sig, err
    assert f"interrupted: by {sig.name}; arm left in zero_velocity (confirmed by the arm)" in err


def test_exit_statuses_for_signals_are_128_plus_the_signal() -> None:
    assert Exit.for_signal(signal.SIGHUP) == Exit.HANGUP == 129
    assert Exit.for_signal(signal.SIGINT) == Exit.INTERRUPTED == 130
    assert Exit.for_signal(signal.SIGQUIT) == Exit.QUIT == 131
    assert Exit.for_signal(signal.SIGTERM) == Exit.TERMINATED == 143


# -- 2: Ctrl-C while the arm's network side hangs ---------------------------------------------


@pytest.fixture
def hanging_link(sim):
    link = HangingLink(sim.udp_address)
    yield link
    link.close()


def test_ctrl_c_while_the_arm_hangs_keeps_sending_the_safe_mode_until_confirmed(
    sim, hanging_link
) -> None:
    proc = driver_process(*_run_argv(hanging_link.url, sim, "--safe-wait", "60"))
    try:
        assert wait_until(lambda: sim.firmware.mode(5) == Mode.CURRENT, timeout=60.0)
        hanging_link.hang.set()
        proc.send_signal(signal.SIGINT)
        # The safe mode is lost in the hang. While the driver holds the link up it resends
        # it; once it judges the link down (about 1 s over UDP) the safe mode is owed and
        # sent on reconnect. Either way it must reach the arm when the hang lifts, which
        # the assertions after it check. The hang lasts 5 s (the attack's) at most.
        assert wait_until(lambda: hanging_link.dropped_safe >= 1, timeout=30.0)
        wait_until(lambda: hanging_link.dropped_safe >= 2 or proc.poll() is not None, 5.0)
        assert proc.poll() is None, "the driver gave up while the arm was silent"
        assert sim.firmware.mode(5) == Mode.CURRENT  # still pushing: nothing got through
        hanging_link.hang.clear()  # the arm answers again
    finally:
        out, err = finish_process(proc)
    assert _modes(sim) == [Mode.ZERO_VELOCITY] * 4, (out, err)
    assert proc.returncode == Exit.INTERRUPTED, err
    # (" after the link came back" when the hang lasted past the stale-link time)
    assert re.search(
        r"interrupted: by SIGINT; arm left in zero_velocity.* \(confirmed by the arm\)", err
    )


def test_ctrl_c_while_the_arm_hangs_past_the_wait_says_it_is_not_confirmed(
    sim, hanging_link
) -> None:
    proc = driver_process(*_run_argv(hanging_link.url, sim, "--safe-wait", "1"), "--json")
    try:
        assert wait_until(lambda: sim.firmware.mode(5) == Mode.CURRENT, timeout=60.0)
        hanging_link.hang.set()
        proc.send_signal(signal.SIGINT)
    finally:
        out, err = finish_process(proc)
    assert sim.firmware.mode(5) == Mode.CURRENT  # the hang outlasted the wait
    assert proc.returncode == Exit.INTERRUPTED, err
    result = json.loads(out)
    assert result["left_in"].startswith("unknown: "), result["left_in"]
    assert "(confirmed by the arm)" not in err and "a safe mode" not in err
    assert "interrupted: by SIGINT; arm left in unknown: " in err
    assert "cut its power" in err  # what to do about an arm that may still be pushing


# -- 4: a move that times out stops the joints -------------------------------------------------


def test_a_move_that_times_out_leaves_the_arm_in_the_safe_mode(sim, capsys) -> None:
    target = sim.snapshot().q + np.array([-1.5, 0.0, 0.0, 0.0])  # about 3 s at the rate limit
    code = main(["--port", str(sim.link), "move", *map(str, target), "--timeout", "1"])
    out, err = capsys.readouterr()
    assert code == Exit.FAILED, err
    assert _modes(sim) == [Mode.ZERO_VELOCITY] * 4  # confirmed before main() returned
    assert "move timed out after 1 s" in err
    assert "arm left in zero_velocity (confirmed by the arm)" in out
    # And E stays where it stopped instead of going on to the target.
    e_stopped = sim.snapshot().q[0]
    assert sim.wait_sim_time(sim.sim_time + 1.0, timeout=30.0)
    assert abs(sim.snapshot().q[0] - e_stopped) < 0.02


# -- 7: NaN or Inf from the arm, or any exception in a controller or a step hook --------------


@pytest.mark.parametrize(
    ("controller", "value"), [("ddpg", float("nan")), ("lambda", float("inf"))]
)
def test_a_non_finite_velocity_ends_the_run_cleanly_with_summary_and_recording(
    sim, tmp_path, capsys, controller, value
) -> None:
    record = tmp_path / "run.rrd"
    target = sim.snapshot().q + np.array([0.3, 0.2, 0.2, 0.2])
    lie_about_velocity(sim, value)
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", controller, "--target", *map(str, target), "--seconds", "5"]
    code = main([*argv, "--json", "--record", str(record)])
    out, err = capsys.readouterr()
    assert code == Exit.FAILED, err
    assert "Traceback" not in err
    result = json.loads(out)
    assert result["exit"] == Exit.FAILED
    assert result["error"].startswith("the arm reported a non-finite velocity (rad/s) at t = ")
    assert f"E (0x05) {value}; no controller was given it" in result["error"]
    assert result["left_in"] == "zero_velocity (confirmed by the arm)"
    assert result["steps"] > 0
    assert _modes(sim) == [Mode.ZERO_VELOCITY] * 4
    recorded = read_recording(record).summary
    assert "non-finite velocity" in str(recorded["stopped_by"])
    assert recorded["left_in"] == "zero_velocity (confirmed by the arm)"

    code = main(argv)  # and as text: the summary, how the arm was left, one line of why
    out, err = capsys.readouterr()
    assert code == Exit.FAILED, err
    assert "Traceback" not in err
    assert "arm left in zero_velocity (confirmed by the arm)" in out
    assert "run failed: the arm reported a non-finite velocity (rad/s)" in out


class Raising:
    """A controller that raises `exc` at its `at`-th step (a bug, or Ctrl-C in its code)."""

    def __init__(self, exc: BaseException, at: int = 3) -> None:
        self.exc, self.at, self.steps = exc, at, 0

    def reset(self) -> None:
        self.steps = 0

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        self.steps += 1
        if self.steps > self.at:
            raise self.exc
        return np.array([0.0, 0.0, 0.0, 50.0])


@pytest.fixture
def client(sim):
    arm = ArmClient(open_transport(udp_url(sim))).start()
    yield arm
    arm.close()


def test_an_exception_in_a_controller_or_a_hook_ends_the_run_with_its_summary(sim, client) -> None:
    q0 = client.read_joints().q
    summary = ControlLoop(client, Raising(RuntimeError("boom")), 0.05).run(q0, 10.0)
    assert summary.error is not None
    assert (
        "the controller failed at t = " in summary.error and "RuntimeError: boom" in summary.error
    )
    assert summary.steps == 3
    assert summary.left_in == "zero_velocity (confirmed by the arm)"
    assert _modes(sim) == [Mode.ZERO_VELOCITY] * 4

    def hook(record) -> None:
        if record.step == 2:
            raise OSError("viewer went away")

    summary = ControlLoop(client, Raising(RuntimeError(), at=10**6), 0.05, on_step=hook).run(
        q0, 10.0
    )
    assert "step hook (recorder or viewer) failed" in (summary.error or "")
    assert summary.left_in == "zero_velocity (confirmed by the arm)"


def test_ctrl_c_inside_a_loop_is_passed_on_with_how_the_arm_was_left(sim, client) -> None:
    q0 = client.read_joints().q
    with pytest.raises(Interrupted) as caught:
        ControlLoop(client, Raising(KeyboardInterrupt()), 0.05).run(q0, 10.0)
    summary = caught.value.summary
    assert summary is not None and summary.steps == 3
    assert (summary.error or "").startswith("interrupted by SIGINT")
    assert caught.value.left_in == summary.left_in == "zero_velocity (confirmed by the arm)"
    assert _modes(sim) == [Mode.ZERO_VELOCITY] * 4
