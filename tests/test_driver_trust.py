"""What the driver refuses to trust: a different arm after a reconnect, motion packets that
would bypass the limit checks, limits the arm reports unasked or out of the factory envelope,
and the hand-overs between the reader thread and callers.

The `loop://` tests inject "arm reports" through the transport itself (the loop echoes them),
so they go round the client's own checks exactly as a hostile arm's frames would.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import threading
import time

import numpy as np
import pytest
from conftest import SimFactory, wait_until

from protocol import DeviceID, Mode, Packet, PacketID, commands
from protocol.alpha5 import JOINTS
from reach_driver import (
    ArmClient,
    DriverError,
    LimitError,
    LimitKind,
    LinkConfig,
    LinkState,
    SafetyConfig,
    open_transport,
)
from reach_driver import errors as driver_errors
from reach_driver.link import ClientStats
from reach_driver.requests import Requester, Waiters
from reach_driver.watchdog import Watchdog
from reach_sim_bridge.emulator.firmware import ALPHA5_DEVICES, FirmwareConfig
from reach_sim_bridge.emulator.server import SimServer

E, D, C, B, A = DeviceID.E, DeviceID.D, DeviceID.C, DeviceID.B, DeviceID.A
BROADCAST = DeviceID.BROADCAST
SPEED = 4.0


def f32(*values: float) -> bytes:
    return struct.pack(f"<{len(values)}f", *values)


def make_client(safety: SafetyConfig | None = None) -> ArmClient:
    arm = ArmClient(
        open_transport("loop://"),
        safety=safety or SafetyConfig(watchdog_s=None),
        link=LinkConfig(stale_link_s=5.0, keepalive_s=2.0),
        request_timeout_s=0.05,
        retries=2,
    )
    return arm.start(discover=False, read_limits=False)


@pytest.fixture
def client():
    arm = make_client()
    yield arm
    arm.close(safe=False)


def arm_reports(client: ArmClient, *packets: Packet) -> None:
    """Frames that arrive as if the arm sent them (the loop echoes the transport's writes)."""
    client.transport.write_frames([p.encode() for p in packets])


def feed_position(client: ArmClient, device: int, value: float) -> None:
    arm_reports(client, Packet(device, PacketID.POSITION, f32(value)))

    def reported() -> bool:
        reading = client.joint(device).position
        return reading is not None and reading.value == pytest.approx(value, abs=1e-6)

    assert wait_until(reported, timeout=2.0)


def answer_requests(client: ArmClient, canned: dict[tuple[int, int], bytes]) -> None:
    """A scripted fake arm on loop://: the echo of each REQUEST is answered from `canned`."""

    def on_packet(packet: Packet, t: float) -> None:
        if packet.packet_id != PacketID.REQUEST:
            return
        replies = [
            Packet(packet.device_id, pid, canned[(int(packet.device_id), pid)])
            for pid in packet.data
            if (int(packet.device_id), pid) in canned
        ]
        if replies:
            arm_reports(client, *replies)

    client.subscribe(on_packet)


def nothing_sent(client: ArmClient, attempt) -> Exception:
    before = client.transport.stats.bytes_out
    with pytest.raises(DriverError) as info:
        attempt()
    assert client.transport.stats.bytes_out == before, "a refused packet reached the wire"
    return info.value


# -- 1. a different arm answering after a reconnect ------------------------------------------


def other_arm(serial_offset: float = 1000.0) -> FirmwareConfig:
    devices = tuple(
        dataclasses.replace(s, serial_number=s.serial_number + serial_offset)
        for s in ALPHA5_DEVICES
    )
    return FirmwareConfig(devices=devices)


def sim_client(link: str, events: list) -> ArmClient:
    arm = ArmClient(
        open_transport(link),
        link=LinkConfig(stale_link_s=0.5, keepalive_s=0.1, backoff_max_s=0.4),
    )
    arm.on_event(events.append)
    return arm.start()


def test_start_reads_the_arms_identity(sim: SimServer) -> None:
    events: list = []
    arm = sim_client(str(sim.link), events)
    try:
        ident = arm.identity
        assert set(ident) == {5, 4, 3, 2, 1}
        assert ident[4].serial_number == 4104.0
        assert ident[4].model_number == 5005.0
        assert ident[4].software_version == "0.1.0"
    finally:
        arm.close()


def test_reconnect_to_a_different_arm_is_refused_and_it_only_gets_the_safe_stop(
    sim_factory: SimFactory,
) -> None:
    first = sim_factory(speed=SPEED)  # both arms on the same link
    link = str(first.link)
    events: list = []
    arm = sim_client(link, events)
    try:
        arm.stream((PacketID.POSITION,), 10, JOINTS)
        q = arm.read_joints((PacketID.POSITION,)).q
        arm.set_mode(JOINTS, Mode.POSITION)
        arm.command_positions(q + 0.05)
        first.stop()  # the link drops mid-move ...
        assert wait_until(lambda: arm.link_state is not LinkState.UP, timeout=10.0)
        second = sim_factory(speed=SPEED, firmware=other_arm())  # ... and another arm answers
        assert wait_until(
            lambda: (
                arm.link_state is not LinkState.DOWN and arm.link_state is not LinkState.PROBING
            ),
            timeout=10.0,
        )
        # The link is failed: not UP (control loops see it as down), and it stays so.
        assert arm.link_state is LinkState.FAILED
        # The new arm was stopped: the last frames the driver wrote it before failing the
        # link, so once the arm has them, whatever was written before them has landed too ...
        assert wait_until(
            lambda: all(second.firmware.mode(int(d)) == Mode.ZERO_VELOCITY for d in JOINTS),
            timeout=20.0,
        )
        # ... and it was not given the old set-up.
        for dev in JOINTS:
            beat = second.firmware.report(int(dev), PacketID.HEARTBEAT_FREQUENCY)
            assert beat is not None and beat.data == b"\x00", f"{dev.name} was set streaming"
        time.sleep(1.0)  # a few probing backoffs (0.4 s at most): no reopening
        assert arm.link_state is LinkState.FAILED
        assert np.isnan(arm.state.q).all()  # the other arm's positions were not accepted
        error_type = driver_errors.ArmIdentityError
        assert issubclass(error_type, DriverError)
        with pytest.raises(error_type, match=r"serial number.*E \(0x05\)|E \(0x05\).*serial"):
            arm.command_positions(q)
        with pytest.raises(error_type):
            arm.request(DeviceID.E, [PacketID.POSITION])
        assert "serial number" in arm.link_reason
        assert any("serial number" in e.message for e in events)
    finally:
        arm.close()


def test_reconnect_to_the_same_arm_after_a_power_cycle_is_accepted(sim: SimServer) -> None:
    events: list = []
    arm = sim_client(str(sim.link), events)
    try:
        arm.stream((PacketID.POSITION,), 10, [DeviceID.E])
        sim.restart(downtime_s=0.3)
        assert wait_until(lambda: arm.stats.reconnects == 1, timeout=10.0)
        assert arm.link_state is LinkState.UP
        n = arm.table.counts.get((5, PacketID.POSITION), 0)
        assert wait_until(
            lambda: arm.table.counts.get((5, PacketID.POSITION), 0) > n + 3, timeout=10.0
        )
    finally:
        arm.close()


# -- 2. one gate for every packet that can move the arm or widen a limit ----------------------


def test_relative_position_is_checked_against_the_current_position_and_bounds() -> None:
    arm = make_client(SafetyConfig(watchdog_s=None, position_bounds={int(E): (2.9, 3.3)}))
    try:
        feed_position(arm, E, 3.2)
        err = nothing_sent(arm, lambda: arm.send(Packet(E, PacketID.RELATIVE_POSITION, f32(1.28))))
        assert isinstance(err, LimitError) and "E (0x05)" in str(err)
        arm.send(Packet(E, PacketID.RELATIVE_POSITION, f32(0.05)))  # 3.25: inside
        nothing_sent(arm, lambda: arm.send(Packet(D, PacketID.RELATIVE_POSITION, f32(0.01))))
        nothing_sent(arm, lambda: arm.send(Packet(E, PacketID.RELATIVE_POSITION, f32(math.nan))))
    finally:
        arm.close(safe=False)


def test_indexed_position_is_refused_unless_allowed(client) -> None:
    feed_position(client, E, 3.0)
    err = nothing_sent(client, lambda: client.send(Packet(E, PacketID.INDEXED_POSITION, f32(0.1))))
    assert "INDEXED_POSITION" in str(err) and "allow_indexed_position" in str(err)
    arm = make_client(SafetyConfig(watchdog_s=None, allow_indexed_position=True))
    try:
        before = arm.transport.stats.bytes_out
        arm.send(Packet(E, PacketID.INDEXED_POSITION, f32(0.1)))
        assert arm.transport.stats.bytes_out > before
    finally:
        arm.close(safe=False)


def test_broadcast_motion_and_limit_packets_are_refused(client) -> None:
    for packet in (
        Packet(BROADCAST, PacketID.RELATIVE_POSITION, f32(0.1)),
        Packet(BROADCAST, PacketID.INDEXED_POSITION, f32(0.1)),
        Packet(BROADCAST, PacketID.CURRENT_LIMITS, f32(100.0, -100.0)),
        commands.mode(BROADCAST, Mode.CURRENT),
    ):
        err = nothing_sent(client, lambda p=packet: client.send(p))
        assert "broadcast" in str(err)
    client.send(commands.mode(BROADCAST, Mode.ZERO_VELOCITY))  # a safe mode may go to all


def test_end_effector_motion_is_refused_naming_the_alternative(client) -> None:
    for pid in (PacketID.KM_END_POS, PacketID.KM_END_VEL):
        err = nothing_sent(client, lambda p=pid: client.send(Packet(E, p, f32(*[0.0] * 6))))
        assert "command_positions" in str(err)


def test_limit_writes_must_be_finite_inside_the_envelope_and_never_wider(client) -> None:
    inf = math.inf
    for maximum, minimum in ((inf, -inf), (700.0, -700.0), (math.nan, -100.0)):
        packet = Packet(E, PacketID.CURRENT_LIMITS, f32(maximum, minimum))
        err = nothing_sent(client, lambda p=packet: client.send(p))
        assert "current" in str(err).lower()
    wide = Packet(E, PacketID.POSITION_LIMITS, f32(7.0, 0.0))
    nothing_sent(client, lambda: client.send(wide))
    client.guard.set_arm_limit(E, LimitKind.CURRENT, (-400.0, 400.0))
    wider = Packet(E, PacketID.CURRENT_LIMITS, f32(500.0, -500.0))
    err = nothing_sent(client, lambda: client.send(wider))
    assert "wider" in str(err)
    nothing_sent(client, lambda: client.write_frames([wider.encode()]))
    before = client.transport.stats.bytes_out
    client.send(Packet(E, PacketID.CURRENT_LIMITS, f32(300.0, -300.0)))  # tighter: fine
    client.send_unchecked(wider)  # the one way round, and its name says so
    assert client.transport.stats.bytes_out > before


def test_motion_to_an_unknown_device_and_unknown_packets_are_refused(client) -> None:
    nothing_sent(client, lambda: client.send(commands.position(0x07, 1.0)))
    nothing_sent(client, lambda: client.send(commands.position(0x30, 1.0)))
    for pid in (PacketID.PRESET_55, PacketID.RESET, PacketID.BOOTLOADER, 0x42, PacketID.SAVE):
        nothing_sent(client, lambda p=pid: client.send(Packet(E, p, b"\x00")))
    # Harmless packets still go out.
    before = client.transport.stats.bytes_out
    client.send(
        commands.request(E, [PacketID.POSITION]),
        commands.heartbeat_set(E, [PacketID.POSITION]),
        commands.heartbeat_frequency(E, 0),
        commands.mode(E, Mode.STANDBY),
    )
    assert client.transport.stats.bytes_out > before


# -- 3. limits the arm reports -----------------------------------------------------------------


def test_unsolicited_limits_are_recorded_but_not_adopted(client) -> None:
    events: list = []
    client.on_event(events.append)
    arm_reports(client, Packet(E, PacketID.POSITION_LIMITS, f32(1e6, -1e6)))
    assert wait_until(lambda: client.joint(E).position_limits is not None, timeout=2.0)
    assert client.joint(E).position_limits.value == (-1e6, 1e6)  # raw, for display
    lim = client.guard.limit(E, LimitKind.POSITION)
    assert (lim.low, lim.high) == pytest.approx((0.0175, 6.143))
    nothing_sent(client, lambda: client.command_position(E, 500.0))
    arm_reports(client, Packet(D, PacketID.CURRENT_LIMITS, f32(math.inf, -math.inf)))
    assert wait_until(lambda: client.joint(D).current_limits is not None, timeout=2.0)
    assert client.guard.limit(D, LimitKind.CURRENT).high == 600.0
    assert client.stats.limits_rejected == 2
    assert sum("limits" in e.message and "E (0x05)" in e.message for e in events) == 1


def test_solicited_limits_are_adopted_only_inside_the_factory_envelope(client) -> None:
    answer_requests(
        client,
        {
            (int(E), PacketID.POSITION_LIMITS): f32(1e30, 0.5),  # asked for, but absurd
            (int(D), PacketID.POSITION_LIMITS): f32(3.0, 0.5),  # asked for and plausible
            (int(D), PacketID.CURRENT_LIMITS): f32(math.inf, -math.inf),
            (int(C), PacketID.VELOCITY_LIMITS): f32(0.3, -0.3),
        },
    )
    got = client.read_limits([E, D, C])
    assert LimitKind.POSITION not in got.get(int(E), {})
    assert got[int(D)][LimitKind.POSITION] == pytest.approx((0.5, 3.0))
    assert LimitKind.CURRENT not in got.get(int(D), {})
    assert got[int(C)][LimitKind.VELOCITY] == pytest.approx((-0.3, 0.3))
    assert client.guard.limit(E, LimitKind.POSITION).high == pytest.approx(6.143)
    assert client.guard.limit(D, LimitKind.POSITION).high == pytest.approx(3.0)
    assert client.guard.limit(D, LimitKind.CURRENT).high == 600.0
    assert client.stats.limits_rejected == 2
    assert any("E (0x05)" in w and "position" in w for w in client.warnings)


# -- 4. hand-overs between threads -------------------------------------------------------------


def test_a_reply_arriving_between_a_timeout_and_the_retry_is_kept() -> None:
    """The late reply to the first REQUEST arrives exactly at the retry boundary (after the
    first wait timed out, before the retry goes out); the device never answers the retry."""
    late = Packet(E, PacketID.POSITION, f32(1.0))
    writes: list[object] = []
    delivered: list[bool] = []

    class Boundary(Waiters):
        def add(self, waiter) -> None:  # type: ignore[no-untyped-def]
            deliver_if_due()
            super().add(waiter)

    waiters = Boundary()

    def deliver_if_due() -> None:
        if writes and not delivered:  # the first REQUEST went out and its wait ran out
            delivered.append(True)
            waiters.offer(late)

    def write(frames) -> None:  # type: ignore[no-untyped-def]
        deliver_if_due()
        writes.append(frames)

    requester = Requester(write, waiters, ClientStats(), "fake://", lambda: True)
    got = requester.request_many([E], [PacketID.POSITION], timeout_s=0.01, retries=1, partial=False)
    assert delivered
    assert got[int(E)][PacketID.POSITION] == late


def test_the_pending_safe_stop_is_handed_over_once() -> None:
    w = Watchdog()
    assert not w.take_safe_pending()
    w.mark_safe_pending()
    results: list[bool] = []
    barrier = threading.Barrier(8)

    def take() -> None:
        barrier.wait()
        results.append(w.take_safe_pending())

    threads = [threading.Thread(target=take) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results.count(True) == 1
    # A loss noted after the hand-over is not wiped by it.
    w.mark_safe_pending()
    assert w.take_safe_pending() and not w.take_safe_pending()


def test_link_loss_and_the_watchdog_share_the_pending_safe_stop(client) -> None:
    client.watchdog.note_sent([commands.velocity(D, 0.1)], now=client.clock())
    client._link_lost("test: cable out")
    assert client.watchdog.take_safe_pending()
