"""The control loop against the virtual arm: arm-time pacing, polling, the per-step hook,
clipping, the soft barrier and how a run ends."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import LOOPBACK, udp_url, wait_until

from protocol import Mode
from reach_driver import ArmClient, ControlLoop, ControlState, Pacing, StepRecord, open_transport

# Real time: a loop late by a period (40 ms of wall time here, 10 ms at 4x) skips a tick, which
# a loaded host makes happen; the runs here count ticks.
SPEED = 1.0


class Constant:
    """A controller that always asks for the same currents."""

    def __init__(self, currents) -> None:
        self.currents = np.asarray(currents, dtype=float)
        self.resets = 0
        self.states: list[ControlState] = []

    def reset(self) -> None:
        self.resets += 1

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        self.states.append(state)
        return self.currents.copy()


@pytest.fixture
def arm_and_sim(sim_factory):
    server = sim_factory(speed=SPEED, pty=False, udp=LOOPBACK)
    client = ArmClient(open_transport(udp_url(server))).start()
    yield client, server
    client.close()


def test_stream_pacing_counts_arm_time_in_heartbeats(arm_and_sim) -> None:
    client, sim = arm_and_sim
    records: list[StepRecord] = []
    controller = Constant([0.0, 0.0, 0.0, 0.0])
    loop = ControlLoop(client, controller, 0.04, on_step=records.append)  # 25 Hz
    q0 = client.read_joints().q
    t0 = sim.sim_time
    summary = loop.run(q0, 1.0)
    assert summary.ok, summary.error
    t = summary.timing
    # 25 heartbeats of arm time; a loop late on a loaded host may take a newer state and skip
    # one, which is counted, never a step at the wrong arm time.
    assert summary.steps == len(records) == t.steps
    assert 23 <= summary.steps <= 25 and summary.steps + t.skipped_states >= 25
    assert controller.resets == 1
    assert [r.step for r in records] == list(range(summary.steps))
    ticks = np.array([r.t for r in records]) / 0.04
    np.testing.assert_allclose(ticks, np.round(ticks), atol=1e-9)  # on the heartbeat grid
    assert ticks[0] == 0 and np.all(np.diff(np.round(ticks)) >= 1) and ticks[-1] <= 24
    assert [s.t for s in controller.states] == [r.t for r in records]
    assert summary.loop_seconds == pytest.approx(1.0)
    assert sim.sim_time - t0 >= 1.0  # the arm really lived through that second
    assert 0 <= t.latency_p50_s <= t.latency_p99_s <= t.latency_max_s
    assert 0 <= t.state_age_p50_s <= t.state_age_max_s
    assert all(r.latency_s >= 0 and r.state_age_s >= 0 for r in records)
    assert wait_until(lambda: all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in (5, 4, 3, 2)))


def test_poll_pacing_requests_the_state_each_period(arm_and_sim) -> None:
    client, sim = arm_and_sim
    records: list[StepRecord] = []
    loop = ControlLoop(
        client, Constant(np.zeros(4)), 0.05, pacing=Pacing.POLL, on_step=records.append
    )
    before = client.stats.requests_sent
    summary = loop.run(client.read_joints().q, 0.5)
    assert summary.ok, summary.error
    assert summary.steps + summary.timing.missed_deadlines >= 9
    assert summary.steps >= 5
    assert client.stats.requests_sent - before >= 4 * summary.steps
    assert all(np.isfinite(r.q).all() and np.isfinite(r.qdot).all() for r in records)


def test_outputs_beyond_the_current_limits_are_clipped_and_counted(arm_and_sim) -> None:
    client, sim = arm_and_sim
    records: list[StepRecord] = []
    loop = ControlLoop(
        client, Constant([5000.0, -5000.0, 0.0, 900.0]), 0.05, on_step=records.append
    )
    q0 = client.read_joints().q
    summary = loop.run(q0, 0.3)
    # every step taken saturated: the 6 ticks of 0.3 s, less any a late loop skipped (counted)
    assert summary.saturated_steps == summary.steps == len(records) >= 1
    assert summary.steps + summary.timing.skipped_states >= 6
    for r in records:
        assert r.saturated
        np.testing.assert_array_equal(r.raw_command_mA, [5000.0, -5000.0, 0.0, 900.0])
        assert r.command_mA[0] <= 600.0 and r.command_mA[1] >= -600.0 and r.command_mA[3] <= 300.0


def test_soft_barrier_keeps_a_joint_pushed_outward_inside_its_bound(sim_factory) -> None:
    hi_c = 3.4034
    sim = sim_factory(speed=SPEED, pty=False, udp=LOOPBACK, start=(3.0, 1.5, hi_c - 0.15, 3.0))
    with ArmClient(open_transport(udp_url(sim))) as client:
        records: list[StepRecord] = []
        loop = ControlLoop(client, Constant([0.0, 0.0, 600.0, 0.0]), 0.05, on_step=records.append)
        summary = loop.run(client.read_joints().q, 2.0)
        assert summary.ok, summary.error
        assert summary.barrier_steps > 0
        assert max(r.q[2] for r in records) < hi_c + 0.02
        assert sim.snapshot().q[2] < hi_c + 0.02
        # Once at the bound the outward current is cut to nothing.
        last = records[-1]
        assert last.command_mA[2] == pytest.approx(0.0, abs=60.0)


def test_a_controller_returning_nan_stops_the_run_and_the_arm_is_left_safe(arm_and_sim) -> None:
    client, sim = arm_and_sim
    summary = ControlLoop(client, Constant([0.0, np.nan, 0.0, 0.0]), 0.05).run(
        client.read_joints().q, 1.0
    )
    assert not summary.ok and "finite" in (summary.error or "")
    assert summary.steps == 0
    assert wait_until(lambda: all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in (5, 4, 3, 2)))


def test_stop_from_the_hook_ends_the_run_early(arm_and_sim) -> None:
    client, _ = arm_and_sim
    loop: ControlLoop

    def hook(r: StepRecord) -> None:
        if r.step == 4:
            loop.stop()

    loop = ControlLoop(client, Constant(np.zeros(4)), 0.05, on_step=hook)
    summary = loop.run(client.read_joints().q, 10.0)
    assert summary.steps == 5 and summary.stopped_by == "stop requested"


def test_bad_arguments_are_refused_before_anything_is_sent(arm_and_sim) -> None:
    client, sim = arm_and_sim
    with pytest.raises(ValueError, match="1..255 Hz"):
        ControlLoop(client, Constant(np.zeros(4)), 0.001)
    loop = ControlLoop(client, Constant(np.zeros(4)), 0.05)
    with pytest.raises(ValueError, match="4 angles"):
        loop.run([1.0, 2.0], 1.0)
    from reach_driver import LimitError

    with pytest.raises(LimitError, match="E \\(0x05\\)"):
        loop.run([7.0, 1.5, 1.5, 3.0], 1.0)
    assert sim.firmware.mode(5) == Mode.STANDBY


@pytest.mark.slow
def test_arm_time_pacing_gives_the_same_run_at_any_simulator_speed(sim_factory) -> None:
    from policy.controllers.pid import make_controller

    finals, sim_seconds = [], []
    # 1x and 3x: 50 and 17 ms of wall time a period, slack enough for a late loop on a loaded
    # host not to skip a tick (a skipped tick is a different run)
    for speed in (1.0, 3.0):
        sim = sim_factory(speed=speed, pty=False, udp=LOOPBACK)
        with ArmClient(open_transport(udp_url(sim))) as client:
            q0 = client.read_joints().q
            t0 = sim.sim_time
            summary = ControlLoop(client, make_controller(), 0.05).run(
                q0 + np.array([0.6, -0.4, 0.5, 1.0]), 3.0
            )
            sim_seconds.append(sim.sim_time - t0)
        sim.stop()
        assert summary.ok and summary.loop_seconds == pytest.approx(3.0)
        finals.append(summary.final_q)
    np.testing.assert_allclose(finals[0], finals[1], atol=0.01)
    assert all(3.0 <= s < 3.5 for s in sim_seconds)  # arm seconds, not wall seconds
