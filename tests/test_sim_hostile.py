"""The served arm against a hostile or confused link: strangers, floods, a slow line.

Every flood here is bounded in count and time and stops by itself (a subprocess that exits
after FLOOD_S, or a loop with a fixed count); traffic stays on loopback. Assertions are on
behaviour (bytes, frames, counters, sim time); the wall-clock limits only make a broken
server fail instead of hang. The one ratio of sim time to wall time (the physics keeps real
time under a flood) has a wide margin because the machine is shared.
"""

from __future__ import annotations

import select
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from protocol import DeviceID, Packet, PacketDecoder, PacketID, commands
from reach_sim_bridge.server import SimConfig, SimServer

A, B, C, D, E = DeviceID.A, DeviceID.B, DeviceID.C, DeviceID.D, DeviceID.E
BROADCAST = DeviceID.BROADCAST
WALL_LIMIT_S = 20.0
FLOOD_S = 2.0
HEARTBEAT_IDS = [PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT]
# Ten ids every device answers: a broadcast request of them asks for 50 replies, 465 bytes
# for its 16.
ASK_ALL = commands.request(
    BROADCAST,
    [
        PacketID.POSITION,
        PacketID.VELOCITY,
        PacketID.CURRENT,
        PacketID.MODE,
        PacketID.SERIAL_NUMBER,
        PacketID.MODEL_NUMBER,
        PacketID.DEVICE_ID,
        PacketID.TEMPERATURE,
        PacketID.HARDWARE_STATUS,
        PacketID.SOFTWARE_VERSION,
    ],
).encode()

# A child process writing `chunk` (stdin) to a pty path (reading what comes back) or a UDP
# address as fast as it can for `seconds`, at most `count` writes; prints the bytes it got
# out. Exits by itself.
FLOODER = r"""
import os, select, socket, sys, time
kind, target, seconds, count = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
chunk = sys.stdin.buffer.read()
sent, end = 0, time.monotonic() + seconds
if kind == "pty":
    fd = os.open(target, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    for _ in range(count):
        if time.monotonic() >= end:
            break
        try:  # read the replies too, so the arm's writes succeed (the costly case)
            while os.read(fd, 65536):
                pass
        except BlockingIOError:
            pass
        try:
            sent += os.write(fd, chunk)
        except BlockingIOError:
            select.select([fd], [fd], [], 0.01)
    os.close(fd)
else:
    host, port = target.rsplit(":", 1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for _ in range(count):
        if time.monotonic() >= end:
            break
        try:
            sock.sendto(chunk, (host, int(port)))
            sent += len(chunk)
        except (BlockingIOError, ConnectionRefusedError):
            pass
print(sent)
"""


def start_flood(
    kind: str, target: str, chunk: bytes, seconds: float = FLOOD_S, count: int = 10_000_000
) -> subprocess.Popen[bytes]:
    proc = subprocess.Popen(
        [sys.executable, "-c", FLOODER, kind, target, str(seconds), str(count)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    assert proc.stdin is not None
    proc.stdin.write(chunk)
    proc.stdin.close()
    return proc


def finish_flood(proc: subprocess.Popen[bytes]) -> int:
    """Bytes the flooder got out; it exits by itself after FLOOD_S."""
    assert proc.wait(timeout=FLOOD_S + WALL_LIMIT_S) == 0
    assert proc.stdout is not None
    with proc.stdout:
        return int(proc.stdout.read())


def udp_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    return sock


def udp_packets(sock: socket.socket) -> list[Packet]:
    out: list[Packet] = []
    while True:
        try:
            data, _ = sock.recvfrom(65535)
        except BlockingIOError:
            return out
        out += PacketDecoder().feed(data)


def udp_collect(sock: socket.socket, srv: SimServer, sim_seconds: float) -> list[Packet]:
    """Everything arriving on `sock` over the next `sim_seconds` of sim time."""
    end = srv.sim_time + sim_seconds
    deadline = time.monotonic() + WALL_LIMIT_S
    got: list[Packet] = []
    while srv.sim_time < end:
        assert time.monotonic() < deadline
        select.select([sock], [], [], 0.01)
        got += udp_packets(sock)
    return got + udp_packets(sock)


def beats(packets: list[Packet], key: tuple[int, int] = (E, PacketID.POSITION)) -> int:
    return sum(p.key == key for p in packets)


# -- hole 1: the UDP peer --------------------------------------------------------------------
@pytest.fixture
def udp_server() -> Iterator[SimServer]:
    with SimServer(SimConfig(speed=4.0, pty=False, udp=("127.0.0.1", 0))) as srv:
        yield srv
        assert srv.error is None


def test_udp_garbage_from_another_port_does_not_take_the_stream(udp_server: SimServer) -> None:
    srv = udp_server
    addr = srv.udp_address
    assert addr is not None
    peer, stranger = udp_socket(), udp_socket()
    try:
        peer.sendto(
            commands.heartbeat_set(E, [PacketID.POSITION]).encode()
            + commands.heartbeat_frequency(E, 50).encode(),
            addr,
        )
        assert beats(udp_collect(peer, srv, 0.3)) >= 5
        before = srv.stats()
        # Garbage of every kind from another local port: 3 stray bytes, a frame with a bad
        # CRC, a lone delimiter, an empty datagram.
        bad_crc = bytearray(commands.request(E, [PacketID.MODE]).encode())
        bad_crc[-2] ^= 0x5A
        for junk in (b"\x13\x37\x42", bytes(bad_crc), b"\x00", b""):
            stranger.sendto(junk, addr)
        got = udp_collect(peer, srv, 1.0)
        assert beats(got) >= 40  # 50 Hz for 1 s of sim time: the stream stayed with the peer
        assert udp_packets(stranger) == []  # no reply, no stream
        after = srv.stats()
        assert after.datagrams_in - before.datagrams_in == 4
        assert after.bad_total > before.bad_total
        assert after.bytes_in - before.bytes_in == 3 + len(bad_crc) + 1
    finally:
        peer.close()
        stranger.close()


def test_udp_stream_follows_the_last_sender_of_a_valid_frame(udp_server: SimServer) -> None:
    srv = udp_server
    addr = srv.udp_address
    assert addr is not None
    first, second = udp_socket(), udp_socket()
    try:
        first.sendto(
            commands.heartbeat_set(E, [PacketID.POSITION]).encode()
            + commands.heartbeat_frequency(E, 50).encode(),
            addr,
        )
        assert beats(udp_collect(first, srv, 0.3)) >= 5
        # A valid frame (even one the arm ignores: device 0x07 is not on this arm) moves the
        # stream to its sender; its request is answered to it as every request is.
        second.sendto(commands.request(0x07, [PacketID.MODE]).encode(), addr)
        srv.wait_sim_time(srv.sim_time + 0.2, timeout=WALL_LIMIT_S)
        udp_packets(first)
        assert beats(udp_collect(second, srv, 0.5)) >= 15
        assert beats(udp_packets(first)) == 0
    finally:
        first.close()
        second.close()
