"""The serial transport and the client on pyserial's `loop://`: what is written comes back.

Echoed commands look like reports from the arm (a POSITION sent to E comes back as a
POSITION from E), which lets these tests check the bytes on the wire, the state table,
request matching, the safety refusals and the watchdog without any arm at all.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import wait_until

from protocol import DeviceID, Mode, Packet, PacketDecoder, PacketID, commands
from reach_driver import (
    ArmClient,
    BadUrlError,
    LimitError,
    LinkConfig,
    NoResponseError,
    RequestTimeoutError,
    SafetyConfig,
    WatchdogTrippedError,
    open_transport,
)
from reach_driver.transport_serial import SerialTransport

E, D, C, B = DeviceID.E, DeviceID.D, DeviceID.C, DeviceID.B


def read_all(transport, settle: float = 0.05) -> bytes:
    out = b""
    end = time.monotonic() + settle
    while True:  # past the deadline, until a read finds nothing: a host pause eats no data
        chunk = transport.read()
        out += chunk
        if not chunk and time.monotonic() >= end:
            return out


def _loop_client(watchdog_s: float = 0.2) -> ArmClient:
    arm = ArmClient(
        open_transport("loop://"),
        safety=SafetyConfig(watchdog_s=watchdog_s),
        link=LinkConfig(stale_link_s=5.0, keepalive_s=2.0),
        request_timeout_s=0.03,
        retries=2,
    )
    return arm.start(discover=False, read_limits=False)


@pytest.fixture
def client():
    arm = _loop_client()
    yield arm
    arm.close(safe=False)


def test_loop_transport_round_trips_frames_and_counts_bytes() -> None:
    t = open_transport("loop://")
    assert isinstance(t, SerialTransport)
    assert t.wire_bytes_per_s == pytest.approx(11520.0)
    frames = [commands.position(1, 1.5).encode(), commands.request(0xFF, [3, 2]).encode()]
    t.write_frames(frames)
    data = read_all(t)
    # the 0x00 written on open first, then the frames
    assert data == bytes.fromhex("00 01 01 07 C0 3F 03 01 08 CB 00 07 03 02 60 FF 06 0B 00")
    assert t.stats.bytes_out == t.stats.bytes_in == len(data)
    t.close()
    assert not t.is_open


def test_bad_serial_urls_and_options_fail_clearly() -> None:
    with pytest.raises(BadUrlError, match="empty port"):
        open_transport("  ")
    with pytest.raises(BadUrlError, match="serial port"):
        open_transport("nosuch://x")
    with pytest.raises(BadUrlError, match="positive"):
        open_transport("loop://", baud=0)


def test_missing_port_names_the_ports_found(tmp_path) -> None:
    from reach_driver import PortNotFoundError

    with pytest.raises(PortNotFoundError, match="no such serial port .*ports found"):
        open_transport(str(tmp_path / "ttyUSB9"))


def test_unreadable_port_says_permission_and_dialout(monkeypatch) -> None:
    import errno

    import serial

    def denied(self) -> None:
        raise serial.SerialException(errno.EACCES, "could not open port: Permission denied")

    monkeypatch.setattr(serial.Serial, "open", denied)
    from reach_driver import PortPermissionError

    with pytest.raises(
        PortPermissionError, match="permission denied opening /dev/ttyUSB0.*dialout"
    ):
        open_transport("/dev/ttyUSB0")


def test_rs485_spaces_frames_and_refuses_broadcast_requests() -> None:
    t = open_transport("loop://", rs485=True)
    assert not t.broadcast_ok
    frames = [commands.velocity(5, 0.0).encode()] * 3
    writes = t.stats.writes  # the 0x00 written on open is one
    t.write_frames(frames)
    assert t.stats.writes - writes == 3  # one write per frame, with a quiet gap before each
    arm = ArmClient(t, link=LinkConfig(stale_link_s=5.0, keepalive_s=2.0))
    arm.start(discover=False, read_limits=False)
    try:
        with pytest.raises(ValueError, match="half-duplex"):
            arm.send(commands.request(0xFF, [PacketID.POSITION]))
        with pytest.raises(ValueError, match="broadcast"):
            arm.request_many([0xFF], [PacketID.POSITION])
    finally:
        arm.close(safe=False)


def test_position_command_goes_out_as_its_wire_bytes_and_updates_state(client) -> None:
    with client.listen() as q:
        client.command_position(E, 3.0)
        got = q.get(timeout=1.0)
    assert got is not None
    packet, t = got
    assert packet == Packet(E, PacketID.POSITION, np.float32(3.0).tobytes())
    assert wait_until(lambda: client.joint(E).position is not None, timeout=2.0)
    reading = client.joint(E).position
    assert reading.value == pytest.approx(3.0) and reading.t == pytest.approx(t)


def test_out_of_limit_position_is_refused_and_nothing_is_sent(client) -> None:
    before = client.transport.stats.bytes_out
    with pytest.raises(LimitError, match=r"joint D \(0x04\).*position limit \[0.0175, 3.403\]"):
        client.command_positions([3.0, 3.9, 1.0, 1.0])  # D is out; E C B are fine
    with pytest.raises(LimitError, match="not finite"):
        client.command_position(E, float("nan"))
    assert client.transport.stats.bytes_out == before
    time.sleep(0.05)
    assert client.stats.packets == 0  # nothing came back either: nothing moved


def test_current_beyond_the_limit_is_refused_by_name(client) -> None:
    client.write_frames([Packet(B, PacketID.POSITION, np.float32(3.0).tobytes()).encode()])
    assert wait_until(lambda: client.joint(B).position is not None, timeout=2.0)
    with pytest.raises(LimitError, match=r"current 350 mA for joint B \(0x02\).*\[-300, 300\]"):
        client.command_current(B, 350.0)


def test_request_matches_device_and_packet_id_and_times_out_with_retries(client) -> None:
    # A POSITION from C must not answer a request for POSITION from E.
    client.write_frames([Packet(C, PacketID.POSITION, np.float32(1.0).tobytes()).encode()])
    with pytest.raises(RequestTimeoutError, match=r"3 attempt.*E \(0x05\): POSITION"):
        client.request(E, [PacketID.POSITION])
    assert client.stats.request_retries == 2
    assert client.stats.request_timeouts == 1


def test_request_is_answered_by_the_matching_packet(client) -> None:
    # The echo of our own REQUEST (id 0x60 from E) is what we ask for here.
    replies = client.request(E, [PacketID.REQUEST])
    assert replies[PacketID.REQUEST] == commands.request(E, [PacketID.REQUEST])


def test_discover_on_a_silent_line_says_nothing_answered(client) -> None:
    with pytest.raises(NoResponseError, match="nothing answered on loop://"):
        client.discover()


def test_listeners_get_every_packet_and_a_failing_one_is_counted(client) -> None:
    seen: list[Packet] = []

    def broken(packet: Packet, t: float) -> None:
        raise RuntimeError("listener bug")

    client.subscribe(broken)
    sub = client.subscribe(lambda p, t: seen.append(p))
    client.set_mode([E, D], Mode.POSITION)
    assert wait_until(lambda: len(seen) == 2, timeout=2.0)
    assert [p.device_id for p in seen] == [E, D]
    assert client.listeners.errors == 2
    sub.cancel()
    client.set_mode(E, Mode.STANDBY)
    time.sleep(0.05)
    assert len(seen) == 2


def test_soft_barrier_cuts_current_pushing_out_and_keeps_current_pulling_in(client) -> None:
    # E's upper bound is 6.143 rad; 0.05 rad inside it is half of the 0.1 rad barrier.
    client.write_frames([Packet(E, PacketID.POSITION, np.float32(6.093).tobytes()).encode()])
    assert wait_until(lambda: client.joint(E).position is not None, timeout=2.0)
    with client.listen() as q:
        sent_out = client.command_current(E, 400.0)
        sent_in = client.command_current(E, -400.0)
        got = [q.get(0.5), q.get(0.5)]
    currents = [item[0].as_float() for item in got if item is not None]
    assert sent_out == pytest.approx(200.0, rel=0.01)
    assert sent_in == -400.0
    assert currents == pytest.approx([sent_out, -400.0], rel=1e-6)
    assert client.guard.barrier_cuts == 1


def test_current_without_a_known_position_is_refused(client) -> None:
    with pytest.raises(LimitError, match="position of joint C .* unknown"):
        client.command_current(C, 10.0)


def test_watchdog_trips_when_commands_stop_and_puts_the_joint_in_zero_velocity(client) -> None:
    client.write_frames([Packet(D, PacketID.POSITION, np.float32(1.0).tobytes()).encode()])
    assert wait_until(lambda: client.joint(D).position is not None, timeout=2.0)
    # Keep the feedback fresh but stop commanding.
    client.command_current(D, 50.0)
    end = time.monotonic() + 10.0  # a deadline: it trips 0.2 s after the command
    while time.monotonic() < end and client.tripped is None:
        client.write_frames([Packet(D, PacketID.POSITION, np.float32(1.0).tobytes()).encode()])
        time.sleep(0.02)
    assert client.tripped is not None and "no command" in client.tripped
    # The MODE it sent comes back through the loop: the joint is in ZERO_VELOCITY.
    assert wait_until(
        lambda: (
            client.joint(D).mode is not None and client.joint(D).mode.value == Mode.ZERO_VELOCITY
        )
    )
    with pytest.raises(WatchdogTrippedError, match="rearm"):
        client.command_current(D, 10.0)
    client.rearm()
    assert client.command_current(D, 10.0) == 10.0


def test_watchdog_trips_on_stale_feedback_while_commanding() -> None:
    # A 1 s watchdog: the commands below come every 20 ms, and only a host pause of 1 s (not
    # of 0.2 s, which a loaded host makes now and then) could make it trip on them instead.
    client = _loop_client(watchdog_s=1.0)
    try:
        client.write_frames([Packet(C, PacketID.POSITION, np.float32(1.0).tobytes()).encode()])
        assert wait_until(lambda: client.joint(C).position is not None, timeout=2.0)
        end = time.monotonic() + 20.0  # a deadline: it trips once the feedback is 1 s stale
        while time.monotonic() < end and client.tripped is None:
            client.command_current(C, 20.0)  # commands keep coming, feedback does not
            time.sleep(0.02)
        tripped = client.tripped
        assert tripped is not None and "stale" in tripped and "C (0x03)" in tripped
        assert client.stats.watchdog_trips == 1
    finally:
        client.close(safe=False)


def test_position_commands_do_not_arm_the_watchdog(client) -> None:
    client.command_position(E, 2.0)
    time.sleep(0.35)
    assert client.tripped is None


def test_commands_fail_fast_when_the_client_is_not_running() -> None:
    from reach_driver import LinkDownError

    arm = ArmClient(open_transport("loop://"))
    with pytest.raises(LinkDownError, match="not running"):
        arm.command_position(E, 2.0)
    arm.transport.close()


def test_decoder_drops_line_noise_and_keeps_the_next_frame() -> None:
    t = open_transport("loop://")
    dec = PacketDecoder()
    t.write(b"\x13\x37\xff\x00" + commands.mode(5, Mode.POSITION).encode())
    packets = dec.feed(read_all(t))
    assert packets == [commands.mode(5, Mode.POSITION)]
    assert dec.stats.bad_total == 1
