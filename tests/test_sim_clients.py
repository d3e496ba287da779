"""Replays of what real clients of the arm put on the wire, against the virtual arm.

The byte patterns come from reading the most used open driver for the Alpha 5 (a ROS 2
driver and the C++ library under it) for what it sends, not from its code: zero-padded
REQUEST lists at 100 Hz, zero-padded HEARTBEAT_SET, mode values the published protocol does
not document, limits in [min, max] order behind eight zero bytes, and the monitor packets. A
real arm answers all of it and shows no lasting fault; so must the emulator.
"""

from __future__ import annotations

import socket
from collections.abc import Iterable

import pytest
from conftest import wait_until

from protocol import (
    DeviceID,
    HardwareStatus,
    Packet,
    PacketDecoder,
    PacketID,
    encode_packet,
)
from reach_sim_bridge.emulator.firmware import Firmware
from reach_sim_bridge.emulator.server import SimConfig, SimServer
from reach_sim_bridge.model.arm import Alpha5Arm

A, B, C, D, E = DeviceID.A, DeviceID.B, DeviceID.C, DeviceID.D, DeviceID.E
JOINTS = (E, D, C, B)
#: What the driver asks of every joint at 100 Hz: a pre-sized list appended to.
PADDED_REQUEST = bytes.fromhex("00 00 00 03 02 05")
POLL_HZ = 100


def wire(device: int, packet_id: int, data: bytes) -> bytes:
    return encode_packet(device, packet_id, data)


def feed(fw: Firmware, decoder: PacketDecoder, chunk: bytes) -> list[Packet]:
    """Wire bytes into the firmware, as the server does; every reply."""
    out: list[Packet] = []
    for packet in decoder.feed(chunk):
        out.extend(fw.handle(packet))
    return out


def poll_frames(devices: Iterable[int] = JOINTS) -> bytes:
    return b"".join(wire(d, PacketID.REQUEST, PADDED_REQUEST) for d in devices)


@pytest.fixture
def fw() -> Firmware:
    return Firmware(Alpha5Arm())


def test_padded_requests_at_100_hz_get_answers_and_no_fault(fw: Firmware) -> None:
    decoder = PacketDecoder()
    seconds = 8.0
    cycles = int(seconds * POLL_HZ)
    answered = 0
    raised = HardwareStatus.NONE
    for _ in range(cycles):
        replies = feed(fw, decoder, poll_frames())
        assert [r.key for r in replies] == [
            (d, p) for d in JOINTS for p in (PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT)
        ]
        answered += len(replies)
        for out in fw.tick(1.0 / POLL_HZ):
            if out.packet_id == PacketID.HARDWARE_STATUS:
                raised |= HardwareStatus.from_bytes(out.data)
        for d in JOINTS:
            raised |= fw.status(d)
    assert answered == cycles * 4 * 3
    assert decoder.stats.bad_frames == {} or not any(decoder.stats.bad_frames.values())
    assert fw.errors.counts == {}, fw.errors.counts
    assert raised == HardwareStatus.NONE, raised.flag_names()
    # The padding is counted, once per padded packet, where the server's stats show it.
    assert fw.ignored.counts["request_padding"] == cycles * 4


def test_heartbeat_set_padding_in_any_slot_streams_the_ids(fw: Firmware) -> None:
    decoder = PacketDecoder()
    # Trailing zeros are the format; leading zeros are a pre-sized list appended to.
    for payload in (bytes([3, 2]) + bytes(8), bytes(8) + bytes([3, 2])):
        assert feed(fw, decoder, wire(D, PacketID.HEARTBEAT_SET, payload)) == []
        assert feed(fw, decoder, wire(D, PacketID.HEARTBEAT_FREQUENCY, b"\x0a")) == []
        out = [p for p in fw.tick(1.0) if p.device_id == D]
        assert [p.packet_id for p in out] == [PacketID.POSITION, PacketID.VELOCITY] * 10
    assert fw.errors.counts == {}
    assert fw.ignored.counts == {"request_padding": 1}
    assert fw.status(D) == HardwareStatus.NONE


#: The "Monitor" packets of protocol V1.12.1 and how many floats each carries.
MONITOR = {
    PacketID.INTERNAL_HUMIDITY: 1,  # 0x65, %
    PacketID.INTERNAL_TEMPERATURE: 1,  # 0x66, deg C
    PacketID.INTERNAL_PRESSURE: 1,  # 0x67, bar
    PacketID.FACTORY_CLIMATE: 3,  # 0x28, [T, P, H]
    PacketID.VOLTAGE: 1,  # 0x90, V
}


def test_every_monitor_packet_is_answered_by_every_device(fw: Firmware) -> None:
    decoder = PacketDecoder()
    ids = bytes(MONITOR)
    for dev in (A, B, C, D, E):
        # Encoded by hand and decoded from the wire: what a client sends and reads back.
        replies = feed(fw, decoder, wire(dev, PacketID.REQUEST, ids))
        back = PacketDecoder().feed(b"".join(r.encode() for r in replies))
        assert [p.key for p in back] == [(dev, pid) for pid in MONITOR]
        values = {p.packet_id: p.floats() for p in back}
        assert all(len(values[pid]) == n for pid, n in MONITOR.items())
        assert values[PacketID.INTERNAL_HUMIDITY] == [pytest.approx(10.0)]
        assert values[PacketID.INTERNAL_TEMPERATURE] == [pytest.approx(20.0)]
        assert values[PacketID.INTERNAL_PRESSURE] == [pytest.approx(1.0)]
        assert values[PacketID.FACTORY_CLIMATE] == pytest.approx([20.0, 1.0, 10.0])
        assert 18.0 < values[PacketID.VOLTAGE][0] <= 24.0
    assert fw.errors.counts == {}
    assert "unsupported_request" not in fw.ignored.counts


#: Mode values the C++ library defines that protocol V1.12.1 does not document.
UNDOCUMENTED_MODES = (0x13, 0x14, 0x17, 0x18, 0x1A, 0x1C)


def test_undocumented_modes_are_ignored_and_counted_without_a_fault(fw: Firmware) -> None:
    decoder = PacketDecoder()
    feed(fw, decoder, wire(E, PacketID.VELOCITY, bytes.fromhex("cd cc 4c 3e")))  # 0.2 rad/s
    for mode in UNDOCUMENTED_MODES:
        for dev in JOINTS:
            assert feed(fw, decoder, wire(dev, PacketID.MODE, bytes([mode]))) == []
        fw.tick(0.05)
    modes = [feed(fw, decoder, wire(d, PacketID.REQUEST, b"\x01"))[0].data[0] for d in JOINTS]
    assert modes == [0x03, 0x00, 0x00, 0x00]  # E still in velocity, the rest in standby
    assert fw.errors.counts == {}
    assert fw.ignored.counts["unimplemented_mode"] == len(UNDOCUMENTED_MODES) * 4
    assert all(fw.status(d) == HardwareStatus.NONE for d in JOINTS)


def test_limits_in_min_max_order_or_the_16_byte_form_are_refused_without_a_fault(
    fw: Firmware,
) -> None:
    from protocol.payload import pack_floats

    decoder = PacketDecoder()
    before = {
        pid: feed(fw, decoder, wire(D, PacketID.REQUEST, bytes([pid])))[0].floats()
        for pid in (PacketID.POSITION_LIMITS, PacketID.VELOCITY_LIMITS, PacketID.CURRENT_LIMITS)
    }
    sent = {
        PacketID.POSITION_LIMITS: (0.5, 3.0),
        PacketID.VELOCITY_LIMITS: (-0.3, 0.3),
        PacketID.CURRENT_LIMITS: (-400.0, 400.0),
    }
    for pid, (lo, hi) in sent.items():
        # The library's bytes: eight zeros (a sizing slip), then [min, max].
        assert feed(fw, decoder, wire(D, pid, bytes(8) + pack_floats(lo, hi))) == []
        # The same without the zeros: [min, max], the order V1.12.1 does not use.
        assert feed(fw, decoder, wire(D, pid, pack_floats(lo, hi))) == []
    after = {
        pid: feed(fw, decoder, wire(D, PacketID.REQUEST, bytes([pid])))[0].floats() for pid in sent
    }
    assert after == before
    assert fw.errors.counts == {"limits_16_bytes": 3, "bad_limits": 3}
    fw.tick(0.1)
    assert fw.status(D) == HardwareStatus.NONE
    # The documented order still works.
    feed(fw, decoder, wire(D, PacketID.CURRENT_LIMITS, pack_floats(400.0, -400.0)))
    reply = feed(fw, decoder, wire(D, PacketID.REQUEST, bytes([PacketID.CURRENT_LIMITS])))
    assert reply[0].floats() == [400.0, -400.0]


# -- the whole client session, over the firmware, a served pty and UDP ------------------------
#: The device ids every device is asked for, once a second.
MONITOR_REQUEST = bytes(MONITOR)
POLL_REPLIES = [PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT]


def client_session(seconds: float) -> list[tuple[float, bytes]]:
    """(sim time, bytes written) of the client's session: its start-up, then the polling."""
    from protocol.payload import pack_floats

    start = b""
    for dev in JOINTS:
        for pid, lo, hi in (
            (PacketID.POSITION_LIMITS, 0.0175, 3.4034),
            (PacketID.VELOCITY_LIMITS, -0.5, 0.5),
            (PacketID.CURRENT_LIMITS, -600.0, 600.0),
        ):
            start += wire(dev, pid, bytes(8) + pack_floats(lo, hi))  # the 16-byte form
        for mode in UNDOCUMENTED_MODES:
            start += wire(dev, PacketID.MODE, bytes([mode]))
    # The jaw streams its position and velocity at 10 Hz from a pre-sized list.
    start += wire(A, PacketID.HEARTBEAT_SET, bytes(8) + bytes([0x03, 0x02]))
    start += wire(A, PacketID.HEARTBEAT_FREQUENCY, b"\x0a")
    events = [(0.0, start)]
    for k in range(int(seconds * POLL_HZ)):
        chunk = poll_frames()
        if k % POLL_HZ == 0:
            chunk += b"".join(wire(d, PacketID.REQUEST, MONITOR_REQUEST) for d in (A, B, C, D, E))
        events.append((k / POLL_HZ, chunk))
    return events


def check_session(replies: list[Packet], seconds: float) -> None:
    """Real-arm answers: every poll and every monitor packet, each decoded; no status."""
    polls = int(seconds * POLL_HZ)
    keys = [p.key for p in replies]
    for dev in JOINTS:
        for pid in POLL_REPLIES:
            assert keys.count((dev, pid)) == polls
    for dev in (A, B, C, D, E):
        for pid, n in MONITOR.items():
            answers = [p for p in replies if p.key == (dev, pid)]
            assert len(answers) == seconds, (dev, pid)  # once a second
            assert all(len(p.floats()) == n for p in answers)
    jaw = [p.packet_id for p in replies if p.device_id == A and p.packet_id in POLL_REPLIES]
    assert len(jaw) >= 2 * 10 * (seconds - 1)  # the jaw's heartbeat
    assert not [p for p in replies if p.packet_id == PacketID.HARDWARE_STATUS]


SESSION_S = 8


def test_client_session_over_the_firmware(fw: Firmware) -> None:
    decoder = PacketDecoder()
    replies: list[Packet] = []
    for at, chunk in client_session(SESSION_S):
        replies += fw.tick(max(0.0, at - fw.time))  # heartbeats and any status
        replies += feed(fw, decoder, chunk)
    replies += fw.tick(1.0 / POLL_HZ)
    raw = b"".join(p.encode() for p in replies)
    check_session(PacketDecoder().feed(raw), SESSION_S)
    assert fw.errors.counts == {"limits_16_bytes": 12}  # refused, counted, no flag
    assert fw.ignored.counts["request_padding"] == SESSION_S * POLL_HZ * 4 + 1
    assert fw.ignored.counts["unimplemented_mode"] == 24
    assert all(fw.status(d) == HardwareStatus.NONE for d in (A, B, C, D, E))


class _PtyClient:
    """The client's end of the served pty: writes a chunk, reads what has arrived."""

    def __init__(self, server: SimServer) -> None:
        import serial

        assert server.pty_path is not None
        self.port = serial.Serial(server.pty_path, 115200, timeout=0.0)

    def write(self, chunk: bytes) -> None:
        self.port.write(chunk)

    def read(self) -> bytes:
        return bytes(self.port.read(self.port.in_waiting or 0))

    def close(self) -> None:
        self.port.close()


class _UdpClient:
    """A UDP client as the Ethernet arms' drivers are: one datagram per write, replies to
    its source port, every datagram waiting read (each may hold several frames)."""

    def __init__(self, server: SimServer) -> None:
        assert server.udp_address is not None
        self.address = server.udp_address
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.datagrams = 0

    def write(self, chunk: bytes) -> None:
        self.sock.sendto(chunk, self.address)
        self.datagrams += 1

    def read(self) -> bytes:
        out = b""
        while True:
            try:
                out += self.sock.recv(65535)
            except BlockingIOError:
                return out

    def close(self) -> None:
        self.sock.close()


ENDPOINTS: dict[str, tuple[SimConfig, type[_PtyClient] | type[_UdpClient]]] = {
    "pty": (SimConfig(speed=4.0), _PtyClient),
    "udp": (SimConfig(speed=4.0, pty=False, udp=("127.0.0.1", 0)), _UdpClient),
}


@pytest.mark.parametrize("endpoint", sorted(ENDPOINTS))
def test_client_session_over_a_served_endpoint(endpoint: str) -> None:
    """The whole session through reach-sim's pty or its UDP socket: real-arm answers (every
    poll, every monitor packet, the jaw's heartbeat), no status report, no flag left."""
    config, make_client = ENDPOINTS[endpoint]
    seconds = 4
    with SimServer(config) as server:
        client = make_client(server)
        decoder = PacketDecoder()
        replies: list[Packet] = []
        t0 = server.sim_time
        try:
            for at, chunk in client_session(seconds):
                assert server.wait_sim_time(t0 + at, timeout=20.0)
                client.write(chunk)
                replies += decoder.feed(client.read())
            assert server.wait_sim_time(server.sim_time + 0.2, timeout=20.0)
            polls = int(seconds * POLL_HZ)

            def every_poll_answered() -> bool:
                # the last answers may still be on their way (a loaded host): wait for them,
                # and a reply that never comes still fails check_session below
                replies.extend(decoder.feed(client.read()))
                keys = [p.key for p in replies]
                return all(keys.count((d, pid)) >= polls for d in JOINTS for pid in POLL_REPLIES)

            wait_until(every_poll_answered, timeout=20.0)
        finally:
            client.close()
        stats = server.stats()
        statuses = server.observe(lambda _arm, fw: [fw.status(d) for d in (A, B, C, D, E)])
        assert server.error is None
    check_session(replies, seconds)
    assert decoder.stats.bad_total == 0
    assert stats.bad_frames == {}
    assert stats.firmware_errors == {"limits_16_bytes": 12}
    assert stats.ignored["request_padding"] == seconds * POLL_HZ * 4 + 1
    assert stats.ignored["unimplemented_mode"] == 24
    assert stats.input_dropped_bytes == 0 and stats.lost_bytes == 0
    if endpoint == "udp":
        assert isinstance(client, _UdpClient)
        assert stats.datagrams_in == client.datagrams == seconds * POLL_HZ + 1
    assert statuses == [HardwareStatus.NONE] * 5
