"""The served virtual arm, through the real pty (pyserial) and UDP, using only the codec.

The server runs faster than real time (--speed) to keep these short. Waits are bounded by
sim time read from the server; the wall-clock limits are only there so a broken server
fails the test instead of hanging it.
"""

from __future__ import annotations

import os
import select
import socket
import termios
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import serial

from protocol import (
    DeviceID,
    HardwareStatus,
    Mode,
    Packet,
    PacketDecoder,
    PacketID,
    commands,
    encode_packet,
)
from reach_sim_bridge.emulator.faults import FaultConfig
from reach_sim_bridge.emulator.server import SimConfig, SimServer

A, B, C, D, E = DeviceID.A, DeviceID.B, DeviceID.C, DeviceID.D, DeviceID.E
BROADCAST = DeviceID.BROADCAST
SPEED = 8.0
WALL_LIMIT_S = 20.0  # generous: the machine is shared


class Client:
    """A host talking to the server over the pty or UDP with nothing but the codec."""

    def __init__(self, server: SimServer, kind: str) -> None:
        self.server = server
        self.kind = kind
        self.decoder = PacketDecoder()
        self.frames_per_datagram: list[int] = []
        self.backlog: list[Packet] = []
        if kind == "pty":
            assert server.pty_path is not None
            self.port: serial.Serial | None = serial.Serial(server.pty_path, 115200, timeout=0.02)
            self.sock: socket.socket | None = None
        else:
            self.port = None
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.settimeout(0.02)

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
        if self.sock is not None:
            self.sock.close()

    def send_raw(self, data: bytes) -> None:
        if self.port is not None:
            self.port.write(data)
            self.port.flush()
        else:
            assert self.sock is not None and self.server.udp_address is not None
            self.sock.sendto(data, self.server.udp_address)

    def send(self, *packets: Packet) -> None:
        """All packets at once: one write, or one datagram holding every frame."""
        self.send_raw(b"".join(p.encode() for p in packets))

    def _read(self) -> list[Packet]:
        if self.port is not None:
            return self.decoder.feed(self.port.read(self.port.in_waiting or 1))
        assert self.sock is not None
        try:
            data, _ = self.sock.recvfrom(65535)
        except TimeoutError:
            return []
        packets = PacketDecoder().feed(data)
        self.frames_per_datagram.append(len(packets))
        self.decoder.feed(data)  # for the statistics
        return packets

    def collect(self, done: Callable[[list[Packet]], bool]) -> list[Packet]:
        got = self.backlog
        self.backlog = []
        deadline = time.monotonic() + WALL_LIMIT_S
        while not done(got):
            assert time.monotonic() < deadline, f"no complete answer; got {got}"
            got.extend(self._read())
        return got

    def ask(self, *packets: Packet) -> list[Packet]:
        """Send requests; the replies they ask for (other traffic is kept for later)."""
        wanted: list[tuple[int, int]] = []
        for p in packets:
            assert p.packet_id == PacketID.REQUEST
            devices = [A, B, C, D, E] if p.device_id == BROADCAST else [p.device_id]
            wanted += [(d, pid) for d in devices for pid in p.data]
        self.send(*packets)
        got = self.collect(lambda ps: _has_in_order(ps, wanted))
        replies, rest = _take(got, wanted)
        self.backlog = rest
        return replies

    def value(self, device: int, pid: int) -> float:
        return self.ask(commands.request(device, [pid]))[0].as_float()

    def wait_sim(self, seconds: float) -> None:
        assert self.server.wait_sim_time(self.server.sim_time + seconds, timeout=WALL_LIMIT_S)


def _has_in_order(got: list[Packet], wanted: list[tuple[int, int]]) -> bool:
    keys = iter(p.key for p in got)
    return all(any(k == w for k in keys) for w in wanted)


def _take(got: list[Packet], wanted: list[tuple[int, int]]) -> tuple[list[Packet], list[Packet]]:
    replies, rest, i = [], [], 0
    for p in got:
        if i < len(wanted) and p.key == wanted[i]:
            replies.append(p)
            i += 1
        else:
            rest.append(p)
    return replies, rest


@pytest.fixture
def server() -> Iterator[SimServer]:
    with SimServer(SimConfig(speed=SPEED, udp=("127.0.0.1", 0))) as srv:
        yield srv
        assert srv.error is None


@pytest.fixture(params=["pty", "udp"])
def client(request: pytest.FixtureRequest, server: SimServer) -> Iterator[Client]:
    c = Client(server, request.param)
    yield c
    c.close()


# -- both transports -------------------------------------------------------------------------
def test_reads_version_serial_limits_and_positions(client: Client) -> None:
    replies = client.ask(
        commands.request(
            E,
            [
                PacketID.SOFTWARE_VERSION,
                PacketID.SERIAL_NUMBER,
                PacketID.POSITION_LIMITS,
                PacketID.CURRENT_LIMITS,
            ],
        )
    )
    assert replies[0].u8s() == [0, 1, 0]
    assert replies[1].as_float() == 4105.0
    assert replies[2].floats() == pytest.approx([6.143, 0.0175])
    assert replies[3].floats() == [600.0, -600.0]
    positions = client.ask(commands.request(BROADCAST, [PacketID.POSITION]))
    truth = client.server.snapshot()
    assert [p.device_id for p in positions] == [A, B, C, D, E]
    for p, q in zip(positions[1:], truth.q[::-1], strict=True):  # B C D E vs E D C B
        assert p.as_float() == pytest.approx(q, abs=0.002)  # still, held in STANDBY


def test_velocity_mode_moves_a_joint_at_the_commanded_rate(client: Client) -> None:
    client.send(commands.velocity(E, 0.3), commands.velocity(C, -0.2))
    client.wait_sim(0.5)
    assert client.value(E, PacketID.VELOCITY) == pytest.approx(0.3, abs=0.01)
    assert client.value(C, PacketID.VELOCITY) == pytest.approx(-0.2, abs=0.01)
    assert client.ask(commands.request(E, [PacketID.MODE]))[0].u8s() == [Mode.VELOCITY]
    # Heartbeats are 0.1 s of sim time apart, however the wall clock behaves.
    client.send(commands.heartbeat_set(E, [PacketID.POSITION]), commands.heartbeat_frequency(E, 10))
    beats = client.collect(lambda ps: sum(p.key == (E, PacketID.POSITION) for p in ps) >= 11)
    q = [p.as_float() for p in beats if p.key == (E, PacketID.POSITION)]
    assert (q[10] - q[0]) / 1.0 == pytest.approx(0.3, abs=0.003)


def test_position_mode_reaches_the_target_within_a_hundredth(client: Client) -> None:
    target_d, target_b = 2.2, 2.6
    client.send(commands.position(D, target_d), commands.position(B, target_b))
    start = client.server.sim_time
    while True:
        d = client.value(D, PacketID.POSITION)
        b = client.value(B, PacketID.POSITION)
        if abs(d - target_d) < 0.01 and abs(b - target_b) < 0.01:
            break
        assert client.server.sim_time - start < 5.0, f"D {d}, B {b} after 5 s of sim time"
        client.wait_sim(0.1)
    client.wait_sim(1.0)
    assert client.value(D, PacketID.POSITION) == pytest.approx(target_d, abs=0.01)


def test_survives_garbage_and_the_empty_mode_packet(client: Client) -> None:
    bad_crc = bytearray(commands.position(E, 1.0).encode())
    bad_crc[-2] ^= 0x5A
    client.send_raw(b"\x00\x13\x37garbage\xff\xff\x00" + bytes(bad_crc))
    client.send_raw(encode_packet(E, PacketID.MODE, b""))  # bytes(Mode.STANDBY) on the wire
    client.send(Packet(E, PacketID.POSITION, b"\x01\x02"))  # wrong payload size
    replies = client.ask(commands.request(E, [PacketID.MODE, PacketID.HARDWARE_STATUS]))
    assert replies[0].u8s() == [Mode.STANDBY]
    status = HardwareStatus.from_bytes(replies[1].data)
    assert HardwareStatus.SERIAL_ERROR in status and HardwareStatus.CRC_ERROR in status
    stats = client.server.stats()
    assert stats.bad_frames.get("crc") == 1
    assert sum(stats.bad_frames.values()) >= 2
    assert stats.firmware_errors == {"bad_payload": 2}
    # The flags are also reported unprompted, once per sim second.
    reports = client.collect(
        lambda ps: sum(p.packet_id == PacketID.HARDWARE_STATUS for p in ps) >= 2
    )
    assert {p.device_id for p in reports if p.packet_id == PacketID.HARDWARE_STATUS} == {E}
    # ... and the arm still moves.
    client.send(commands.velocity(E, 0.2))
    client.wait_sim(0.5)
    assert client.value(E, PacketID.VELOCITY) == pytest.approx(0.2, abs=0.01)


def test_heartbeat_streams_packets(client: Client) -> None:
    client.send(
        commands.heartbeat_set(D, [PacketID.POSITION, PacketID.CURRENT]),
        commands.heartbeat_frequency(D, 20),
    )
    beats = client.collect(lambda ps: sum(p.key == (D, PacketID.CURRENT) for p in ps) >= 5)
    keys = [p.key for p in beats if p.device_id == D]
    assert keys[:4] == [(D, PacketID.POSITION), (D, PacketID.CURRENT)] * 2


# -- pty only --------------------------------------------------------------------------------
def test_control_bytes_pass_through_pyserial_unechoed(server: SimServer) -> None:
    client = Client(server, "pty")
    try:
        # Velocity limits whose float bytes hold CR, LF, ^C, XON/XOFF and DEL.
        tricky = bytes([0x0D, 0x0A, 0x03, 0x3F]), bytes([0x11, 0x13, 0x7F, 0xBF])
        packet = Packet(E, PacketID.VELOCITY_LIMITS, tricky[0] + tricky[1])
        hi, lo = packet.floats()
        client.send(packet)
        reply = client.ask(commands.request(E, [PacketID.VELOCITY_LIMITS]))[0]
        assert reply.data == tricky[0] + tricky[1]
        assert reply.floats() == [hi, lo]
        client.wait_sim(0.2)
        # Nothing else came back: an echo would decode as our own two packets.
        assert client.port is not None  # a pty client
        assert client.backlog == [] and client.decoder.feed(client.port.read(4096)) == []
        assert client.decoder.stats.bad_total == 0
    finally:
        client.close()


def test_pty_is_raw_for_clients_that_do_not_configure_it(server: SimServer) -> None:
    # A plain open() (cat, a C program) keeps the tty's settings: they must already be raw,
    # else the line discipline would echo replies back into the arm and turn CR into LF.
    assert server.pty_path is not None
    fd = os.open(server.pty_path, os.O_RDWR | os.O_NOCTTY)
    try:
        lflag = termios.tcgetattr(fd)[3]
        assert not lflag & (termios.ECHO | termios.ICANON | termios.ISIG)
        limits = bytes([0x0D, 0x0A, 0x03, 0x3F, 0x11, 0x13, 0x7F, 0xBF])
        os.write(
            fd,
            Packet(C, PacketID.POSITION_LIMITS, limits).encode()
            + commands.request(C, [PacketID.POSITION_LIMITS]).encode(),
        )
        expected = Packet(C, PacketID.POSITION_LIMITS, limits).encode()
        received = b""
        deadline = time.monotonic() + WALL_LIMIT_S
        while len(received) < len(expected):
            assert time.monotonic() < deadline
            if select.select([fd], [], [], 0.05)[0]:
                received += os.read(fd, 4096)
        assert received == expected
        server.wait_sim_time(server.sim_time + 0.2, timeout=WALL_LIMIT_S)
        assert server.stats().frames_in == 2  # our reply was not echoed back into the arm
    finally:
        os.close(fd)


def test_torque_scale_slows_a_joint() -> None:
    speeds = {}
    for scale in (1.0, 0.1):
        faults = FaultConfig(torque_scale=(scale, 1.0, 1.0, 1.0))
        with SimServer(SimConfig(speed=SPEED, faults=faults)) as srv:
            client = Client(srv, "pty")
            client.send(commands.velocity(E, 0.5))
            client.wait_sim(1.0)
            speeds[scale] = client.value(E, PacketID.VELOCITY)
            client.close()
    assert speeds[1.0] == pytest.approx(0.5, abs=0.01)
    assert speeds[0.1] < 0.6 * speeds[1.0]


def test_link_symlink_follows_the_pty_and_is_removed(tmp_path: Path) -> None:
    link = tmp_path / "alpha5"
    srv = SimServer(SimConfig(speed=SPEED, link=str(link)))
    path = srv.start()
    try:
        assert os.readlink(link) == path
        with serial.Serial(str(link), 115200, timeout=0.02) as port:
            port.write(commands.request(B, [PacketID.DEVICE_ID]).encode())
            dec = PacketDecoder()
            got: list[Packet] = []
            deadline = time.monotonic() + WALL_LIMIT_S
            while not got:
                assert time.monotonic() < deadline
                got = dec.feed(port.read(64))
            assert got == [Packet(B, PacketID.DEVICE_ID, b"\x02")]
    finally:
        srv.stop()
    assert not link.exists() and not link.is_symlink()


def test_link_never_replaces_a_real_file(tmp_path: Path) -> None:
    precious = tmp_path / "data"
    precious.write_text("keep me")
    with pytest.raises(FileExistsError, match="not a symlink"):
        SimServer(SimConfig(link=str(precious))).start()
    assert precious.read_text() == "keep me"


def test_restart_keeps_the_link_and_udp_port_and_resets_the_arm(tmp_path: Path) -> None:
    link = tmp_path / "alpha5"
    srv = SimServer(SimConfig(speed=SPEED, link=str(link), udp=("127.0.0.1", 0)))
    srv.start()
    try:
        udp = srv.udp_address
        client = Client(srv, "udp")
        q_start = client.value(E, PacketID.POSITION)
        client.send(commands.velocity(E, 0.5))
        client.wait_sim(1.0)
        assert client.value(E, PacketID.POSITION) > q_start + 0.3
        srv.restart()
        assert srv.udp_address == udp and os.readlink(link) == srv.pty_path
        assert client.value(E, PacketID.POSITION) == pytest.approx(q_start, abs=0.002)
        assert client.ask(commands.request(E, [PacketID.MODE]))[0].u8s() == [Mode.STANDBY]
        client.send(commands.velocity(E, 0.5))
        client.wait_sim(1.0)
        srv.power_cycle()  # endpoints stay open
        assert client.value(E, PacketID.POSITION) == pytest.approx(q_start, abs=0.002)
        client.close()
    finally:
        srv.stop()
    assert srv.error is None


# -- UDP specifics ---------------------------------------------------------------------------
def test_udp_answers_several_frames_per_datagram_one_frame_per_reply(server: SimServer) -> None:
    client = Client(server, "udp")
    try:
        replies = client.ask(
            commands.request(D, [PacketID.POSITION, PacketID.VELOCITY]),
            commands.request(BROADCAST, [PacketID.MODE]),
        )
        assert [p.key for p in replies] == [(D, PacketID.POSITION), (D, PacketID.VELOCITY)] + [
            (d, PacketID.MODE) for d in (A, B, C, D, E)
        ]
        assert client.frames_per_datagram[:7] == [1] * 7
        # A frame without its terminator: the datagram's end ends the frame.
        client.send_raw(commands.request(C, [PacketID.DEVICE_ID]).encode()[:-1])
        got = client.collect(lambda ps: any(p.key == (C, PacketID.DEVICE_ID) for p in ps))
        assert Packet(C, PacketID.DEVICE_ID, b"\x03") in got
        assert server.stats().datagrams_in == 2
    finally:
        client.close()


def test_udp_only_server_binds_loopback_port() -> None:
    with SimServer(SimConfig(pty=False, udp=("127.0.0.1", 0))) as srv:
        assert srv.pty_path is None
        host, port = srv.udp_address or ("", 0)
        assert host == "127.0.0.1" and port > 0
        client = Client(srv, "udp")
        assert client.ask(commands.request(A, [PacketID.DEVICE_ID]))[0].u8s() == [1]
        client.close()


# -- link faults -----------------------------------------------------------------------------
def test_drop_rate_one_loses_every_reply() -> None:
    with SimServer(SimConfig(speed=SPEED, faults=FaultConfig(drop_rate=1.0))) as srv:
        client = Client(srv, "pty")
        for _ in range(5):
            client.send(commands.request(E, [PacketID.POSITION]))
        stats_wait = time.monotonic() + WALL_LIMIT_S
        while srv.stats().dropped_frames < 5:
            assert time.monotonic() < stats_wait
            time.sleep(0.01)
        client.wait_sim(0.2)
        assert client.port is not None  # a pty client
        assert client.decoder.feed(client.port.read(4096)) == []
        assert srv.stats().frames_out == 0
        client.close()


def test_corrupt_rate_damages_bytes_the_client_detects() -> None:
    faults = FaultConfig(corrupt_rate=0.2)
    with SimServer(SimConfig(speed=SPEED, faults=faults, seed=3)) as srv:
        client = Client(srv, "pty")
        for _ in range(20):
            client.send(commands.request(BROADCAST, [PacketID.POSITION]))
        deadline = time.monotonic() + WALL_LIMIT_S
        while srv.stats().bytes_out < srv.stats().frames_out * 10 or srv.stats().frames_out < 100:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        client.wait_sim(0.2)
        assert client.port is not None  # a pty client
        good = client.decoder.feed(client.port.read(65536))
        stats = srv.stats()
        assert stats.corrupted_bytes > 0
        assert client.decoder.stats.bad_total > 0
        assert len(good) < 100  # some replies did not survive
        client.close()


def test_latency_and_baud_throttle_keep_frames_intact_and_in_order() -> None:
    config = SimConfig(speed=SPEED, baud=9600, faults=FaultConfig(latency_ms=30.0))
    with SimServer(config) as srv:
        client = Client(srv, "pty")
        replies = client.ask(
            commands.request(BROADCAST, [PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT])
        )
        assert len(replies) == 15
        assert client.decoder.stats.bad_total == 0
        client.close()


def test_start_pose_and_bad_config_are_checked() -> None:
    srv = SimServer(SimConfig(pty=False, udp=("127.0.0.1", 0), start=(1.0, 0.5, 2.0, 4.0)))
    assert srv.snapshot().q == pytest.approx([1.0, 0.5, 2.0, 4.0])
    with pytest.raises(ValueError, match="outside the joint ranges"):
        SimServer(SimConfig(start=(1.0, 3.9, 2.0, 4.0)))
    with pytest.raises(ValueError, match="nothing to serve"):
        SimConfig(pty=False)
    with pytest.raises(ValueError, match="speed"):
        SimConfig(speed=0.0)
