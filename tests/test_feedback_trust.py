"""Feedback the control loop must not take as truth: one-tick position glitches (1e6, 6.2, -1
rad) are held at the last good state, counted and reported; a glitch that lasts, or a
velocity the arm stops sending, ends the run with the arm made safe. The virtual arm is
made to lie by replacing what its firmware reports for E (a sensor fault it has no switch
for, `policy.campaigns.attacks`); every run counts arm time in heartbeats."""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

import numpy as np
from conftest import FEEDBACK_TIMEOUT_S, LOOPBACK, udp_url, wait_until

from policy.campaigns.attacks import glitch_position, silence_velocity, stick_velocity
from protocol import DeviceID, Mode, PacketID, commands
from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINTS, MAX_JOINT_SPEED
from reach_driver import ArmClient, ControlLoop, ControlState, SafetyConfig, open_transport
from reach_driver.plausibility import FeedbackCheck
from reach_driver.stream_rate import RateCheck

E = DeviceID.E
PERIOD = 0.05


class Hold:
    """A PD controller holding the angles it first saw; keeps every state it was given."""

    def __init__(self) -> None:
        self.states: list[ControlState] = []
        self.q0: np.ndarray | None = None

    def reset(self) -> None:
        self.states.clear()
        self.q0 = None

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        self.states.append(state)
        if self.q0 is None:
            self.q0 = state.q.copy()
        return 400.0 * (self.q0 - state.q) - 200.0 * state.qdot


def _client(server: Any) -> ArmClient:
    return ArmClient(open_transport(udp_url(server))).start()


def _plausible(states: list[ControlState]) -> None:
    """Every state a controller saw lies in the envelope and moved no faster than physics."""
    lo = np.array([FACTORY_POSITION_LIMITS[d][0] for d in JOINTS]) - 0.1
    hi = np.array([FACTORY_POSITION_LIMITS[d][1] for d in JOINTS]) + 0.1
    q = np.array([s.q for s in states])
    t = np.array([s.t for s in states])
    assert np.all((q >= lo) & (q <= hi)), q[~np.all((q >= lo) & (q <= hi), axis=1)]
    steps = np.abs(np.diff(q, axis=0))
    allowed = np.outer(np.diff(t), MAX_JOINT_SPEED) + 0.05
    assert np.all(steps <= allowed), steps.max(axis=0)


def test_one_tick_position_glitches_are_held_counted_and_reported(sim_factory) -> None:
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    sent = glitch_position(server, [1e6, 6.2, -1.0])
    client = _client(server)
    try:
        controller = Hold()
        q0 = client.read_joints().q
        summary = ControlLoop(client, controller, PERIOD).run(q0, 3.2)
    finally:
        client.close()
    assert len(sent) >= 3  # 1e6, 6.2 and -1 each went out once
    assert summary.ok, summary.error
    _plausible(controller.states)
    assert summary.implausible_samples >= 1
    assert any(e.startswith("implausible feedback:") for e in summary.events), summary.events
    assert "E: position" in " ".join(summary.events)
    assert summary.trace is not None and np.all(np.abs(summary.trace.q[:, 0]) < 10)


def test_a_glitch_that_lasts_ends_the_run_with_the_arm_safe(sim_factory) -> None:
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    firmware = server.firmware
    honest = firmware._noisy_position

    def stuck(d: Any) -> float:  # E reads 6.2 rad for good once in current mode
        if d.spec.device_id == E and firmware.mode(int(E)) == Mode.CURRENT:
            return 6.2
        return honest(d)

    firmware._noisy_position = stuck
    client = _client(server)
    try:
        controller = Hold()
        summary = ControlLoop(client, controller, PERIOD).run(client.read_joints().q, 5.0)
    finally:
        client.close()
    assert not summary.ok
    assert "implausible feedback from E" in str(summary.error), summary.error
    assert "6.2" in str(summary.error)
    assert summary.loop_seconds < 1.0  # held for at most the stale limit, not the run
    assert summary.left_in == "zero_velocity (confirmed by the arm)"
    _plausible(controller.states)
    assert server.firmware.mode(int(E)) == Mode.ZERO_VELOCITY


def test_a_velocity_the_arm_stops_sending_ends_the_run_naming_it(sim_factory) -> None:
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    silence_velocity(server, 0.5)  # E's VELOCITY stops 0.5 s into current mode
    client = _client(server)
    try:
        summary = ControlLoop(client, Hold(), PERIOD).run(client.read_joints().q, 11.0)
    finally:
        client.close()
    assert not summary.ok
    # The watchdog (wall time) or the loop (arm time) trips first: either names both.
    assert "E (0x05) velocity" in str(summary.error), summary.error
    assert "stale" in str(summary.error)
    assert summary.loop_seconds < 2.0
    assert summary.left_in == "zero_velocity (confirmed by the arm)"


def test_a_velocity_stuck_while_the_joint_moves_is_implausible_one_at_rest_is_not() -> None:
    """A repeated velocity proves nothing (an arm at rest reports 0.0 for ever); one that
    disagrees with how far the joint moved meanwhile is a stuck sensor."""
    rng = np.random.default_rng(0)
    q = np.array([3.0, 1.5, 1.5, 3.0])
    still = np.zeros(4)
    check = FeedbackCheck()  # at rest: exactly 0.0 for 30 s, positions with sensor noise
    for k in range(600):
        assert not check.check(k * PERIOD, q + rng.normal(0.0, 0.002, 4), still).bad.any()
    check = FeedbackCheck()  # a steady 0.5 rad/s, reported identically, positions following
    for k in range(20):
        t = k * PERIOD
        assert not check.check(t, q + 0.5 * t, np.full(4, 0.5)).bad.any()
    check = FeedbackCheck()  # E's velocity stuck at 0 while E moves 0.5 rad/s
    check.check(0.0, q, still)
    moved = q + np.array([0.5 * PERIOD, 0.0, 0.0, 0.0])
    verdict = check.check(PERIOD, moved, still)
    assert verdict.bad.tolist() == [True, False, False, False]
    assert verdict.why[0].startswith("E: velocity stuck at 0 rad/s"), verdict.why
    check = FeedbackCheck()  # the same, but the velocity was held over a lost packet
    check.check(0.0, q, still)
    held = np.array([False, True, True, True])
    assert not check.check(PERIOD, moved, still, fresh=held).bad.any()
    check = FeedbackCheck()  # stuck at 0.8 rad/s once the joint has stopped
    check.check(0.0, q, np.full(4, 0.8))
    assert check.check(PERIOD, q, np.full(4, 0.8)).bad.all()


def test_the_rate_is_measured_on_reported_plausible_changing_velocities_only() -> None:
    """Of four joints moving or held, only E's samples measure the rate: D's velocity repeats
    one value (stuck at 0.8 rad/s while D moves 0.5: read as the truth it made 20 Hz look
    like 32), C is held at its last good sample (moved 0 while its held velocity says 0.5)."""
    rate = RateCheck(20)
    ok = np.array([True, True, False, True])
    for k in range(40):
        t = k / 20
        q = np.array([1.0 + 0.5 * t, 1.0 + 0.5 * t, 1.0, 1.0])
        qdot = np.array([0.5 + 0.001 * (k % 2), 0.8, 0.5, 0.0])
        rate.update(k, q, qdot, ok)
    assert rate.measured_hz is not None and abs(rate.measured_hz - 20.0) < 0.2


def test_a_hard_start_does_not_pass_for_a_wrong_rate() -> None:
    """Six light joints reaching their top speed (1.5 rad/s, time constant 10 ms) within the
    first tick: between the first two samples each moves nearly top speed x the period, while
    the mean of its two velocity samples (a third of top speed, then top speed) says two
    thirds of it, which read as a stream 35 % slow and stopped a Bravo 7's run 0.1 s in. An
    interval whose speed more than doubled does not measure the rate; steady ones do."""
    top, tau, t0 = 1.5, 0.01, 0.004

    def sample(t: float) -> tuple[np.ndarray, np.ndarray]:
        s = t + t0
        q = 1.0 + top * (s - tau * (1.0 - np.exp(-s / tau)))
        return np.full(6, q), np.full(6, top * (1.0 - np.exp(-s / tau)))

    rate = RateCheck(20)
    for k in range(2):
        rate.update(k, *sample(k / 20))
    assert not rate.off(), rate.measured_hz
    for k in range(2, 6):
        rate.update(k, *sample(k / 20))
    assert rate.measured_hz is not None and abs(rate.measured_hz - 20.0) < 0.5


def test_ticks_lost_whole_are_seen_as_a_gap_and_estimated() -> None:
    """The assembler counts ticks by the order of their packets, so ticks lost whole leave no
    trace there; a tick that begins 0.4 s after the one before, where ticks come every
    0.05 s, follows a gap that could have held 7 of them (`Tick.lost`)."""
    from protocol import Packet
    from protocol.payload import pack_floats
    from reach_driver.assembler import StateAssembler

    asm = StateAssembler(PERIOD)
    lost = []
    t = 0.0
    for k in range(12):
        t += 0.4 if k == 8 else PERIOD
        for i, dev in enumerate(JOINTS):
            for pid in (PacketID.POSITION, PacketID.VELOCITY):
                asm(Packet(dev, pid, pack_floats(1.0 + 0.01 * k + 0.001 * i)), t + 0.001 * i)
        got = asm.take(0.0)
        assert got is not None
        lost.append(got.lost)
    assert lost == [0] * 8 + [7] * 4
    assert asm.gaps == 1


def test_a_velocity_stuck_at_one_value_while_the_joint_moves_ends_the_run_naming_it(
    sim_factory,
) -> None:
    """E's VELOCITY sticks at its value 0.2 s (arm time) into the run while E is still on
    its way (the emulator's `StuckReading`): the packets keep coming, so nothing is stale, but
    the run must stop naming the stuck velocity, with the arm safe, and the stuck value must
    not pass for a wrong stream rate (it did: "the arm streams at 26.7 Hz")."""
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    stick_velocity(server, 0.2)
    summary = _reach_run(server, 6.0, np.array([1.0, 0.2, -0.2, 0.3]))
    assert not summary.ok
    error = str(summary.error)
    assert "implausible feedback from E (0x05)" in error, error
    assert "E: velocity stuck at" in error
    assert summary.loop_seconds < 3.0
    assert summary.left_in == "zero_velocity (confirmed by the arm)"
    assert summary.measured_hz is None or abs(summary.measured_hz - 20.0) < 2.0


class Reach:
    """A PD controller to the target, saturating: the joints move, so the rate is measurable."""

    def reset(self) -> None:
        pass

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        return np.clip(3000.0 * (target - state.q) - 300.0 * state.qdot, -500.0, 500.0)


def stream_at(server: Any, factor: float) -> None:
    """The arm streams at `factor` x the heartbeat frequency asked (a firmware that halves or
    doubles it)."""
    from protocol import Packet, PacketID

    firmware = server.firmware
    honest = firmware._handlers[PacketID.HEARTBEAT_FREQUENCY]

    def wrong(targets: Any, packet: Packet) -> Any:
        hz = packet.data[0]
        return honest(
            targets, Packet(packet.device_id, packet.packet_id, bytes((round(hz * factor),)))
        )

    firmware._handlers[PacketID.HEARTBEAT_FREQUENCY] = wrong


def _reach_run(server: Any, seconds: float, move: np.ndarray | None = None, **loop: Any) -> Any:
    # A 1 s watchdog and a 5 s wait for a state: a loaded host's stall is not what these runs
    # are about (the state timeout's own test sets it back).
    loop.setdefault("state_timeout_s", FEEDBACK_TIMEOUT_S)
    client = ArmClient(open_transport(udp_url(server)), safety=SafetyConfig(watchdog_s=1.0))
    client.start()
    try:
        q0 = client.read_joints().q
        target = q0 + (np.array([0.4, 0.2, -0.2, 0.3]) if move is None else move)
        return ControlLoop(client, Reach(), PERIOD, **loop).run(target, seconds)
    finally:
        client.close()


def test_a_stream_at_the_rate_asked_is_measured_and_passes(sim_factory) -> None:
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    summary = _reach_run(server, 3.0)
    assert summary.ok, summary.error
    assert summary.measured_hz is not None and abs(summary.measured_hz - 20.0) < 2.0
    assert summary.duplicate_packets == 0


def test_an_arm_streaming_at_half_or_double_the_rate_asked_stops_the_run(sim_factory) -> None:
    for factor, shown in ((0.5, "10"), (2.0, "40")):
        server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
        stream_at(server, factor)
        summary = _reach_run(server, 6.0)
        assert not summary.ok
        error = str(summary.error)
        assert error.startswith("the arm streams at "), error
        assert "asked 20 Hz" in error
        measured = float(error.split("the arm streams at ")[1].split(" Hz")[0])
        assert abs(measured / float(shown) - 1) < 0.15, error
        assert summary.loop_seconds < 3.0
        assert summary.left_in == "zero_velocity (confirmed by the arm)"
        server.stop()


def test_every_packet_twice_is_dropped_and_counted_not_blamed_on_the_feedback(
    sim_factory,
) -> None:
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    firmware = server.firmware
    honest = firmware.steps  # what the server sends unprompted: the heartbeats
    firmware.steps = lambda n: [p for p in honest(n) for _ in (0, 1)]
    summary = _reach_run(server, 3.0)
    assert summary.ok, summary.error
    assert summary.duplicate_packets > 100  # 8 a tick, 60 ticks
    assert summary.steps + summary.timing.skipped_states >= 55
    assert summary.measured_hz is not None and abs(summary.measured_hz - 20.0) < 2.0


def test_the_top_speed_the_check_allows_is_above_what_the_motors_can_do() -> None:
    from reach_sim_bridge.model.motor import no_load_speed

    assert np.all(no_load_speed(supply_voltage=30.0) < np.asarray(MAX_JOINT_SPEED))


def _other_client(
    server: Any, seconds: float, every_s: float = 0.01
) -> tuple[threading.Thread, list[float]]:
    """Another client on the arm's UDP port: once E is well under way (0.2 s into current
    mode), a request every `every_s` for `seconds`, so the arm streams to it meanwhile
    (A3-6; the run's own writes take the stream back until the next request)."""
    host, port = server.udp_address
    took: list[float] = []

    def other() -> None:
        assert wait_until(lambda: server.firmware.mode(int(E)) == Mode.CURRENT, timeout=30.0)
        time.sleep(0.2)
        ask = commands.request(DeviceID.B, [PacketID.MODE]).encode()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                sock.sendto(ask, (host, port))
                time.sleep(every_s)
        took.append(server.sim_time)

    thread = threading.Thread(target=other, daemon=True)
    thread.start()
    return thread, took


def test_a_second_udp_client_taking_the_stream_a_while_is_not_read_as_a_wrong_rate(
    sim_factory,
) -> None:
    """The udp-second-client case (A3-6) where the run goes on: while a run drives E at full
    speed, another client writes to the arm's UDP port for 0.3 s (what `info` does), so the
    arm streams to it and the run's ticks are lost whole, which the loop does not count as
    arm time. E's real motion across that gap was taken for position glitches (E held at its
    last good sample) and the held samples for a 27-30 Hz stream of a 20 Hz one: the run
    stopped on "the arm streams at 26.9 Hz". The gap is now seen (`stream_gaps`), the jump
    check allows for the ticks it could have held and the rate check skips it."""
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    thread, took = _other_client(server, 0.3)
    summary = _reach_run(server, 3.0, np.array([1.5, 0.2, -0.2, 0.3]))
    thread.join(timeout=30.0)
    assert took, "the other client never wrote"
    assert summary.ok, summary.error
    assert summary.timing.stream_gaps >= 1 and summary.timing.lost_ticks >= 4
    assert summary.implausible_samples == 0, summary.events
    assert summary.measured_hz is not None and abs(summary.measured_hz - 20.0) < 2.0


def test_a_second_udp_client_holding_the_stream_past_the_state_timeout_is_named(
    sim_factory,
) -> None:
    """The loop's own state timeout (0.5 s without a state, before the 1 s watchdog) over
    UDP asks the arm why (`ArmClient.stream_problem`): it names the other client, and the
    arm is made safe."""
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    thread, _ = _other_client(server, 3.0, every_s=0.002)
    summary = _reach_run(server, 6.0, np.array([1.5, 0.2, -0.2, 0.3]), state_timeout_s=0.5)
    thread.join(timeout=30.0)
    assert not summary.ok
    error = str(summary.error)
    assert error.startswith("feedback stopped: no complete state for 0.50 s"), error
    assert "another client on this arm's UDP port took the stream" in error
    assert summary.left_in == "zero_velocity (confirmed by the arm)"


def test_the_wait_for_a_state_is_never_shorter_than_the_watchdog(sim_factory) -> None:
    """Without a state there is no command, and the watchdog makes the arm safe after its
    limit anyway: `--watchdog` raised for a busy machine must also lengthen the wait."""
    server = sim_factory(speed=1.0, pty=False, udp=LOOPBACK)
    for watchdog_s, period_s, given, expected in (
        (1.0, PERIOD, None, 1.0),  # a raised watchdog
        (0.2, PERIOD, None, 0.5),  # the default watchdog: the default wait
        (None, PERIOD, None, 0.5),  # no watchdog
        (1.0, PERIOD, 0.3, 0.3),  # a wait given is kept
    ):
        client = ArmClient(
            open_transport(udp_url(server)), safety=SafetyConfig(watchdog_s=watchdog_s)
        )
        try:
            loop = ControlLoop(client, Reach(), period_s, state_timeout_s=given)
            assert loop.state_timeout_s == expected, (watchdog_s, given)
        finally:
            client.close()
