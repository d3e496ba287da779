"""The served arm against a hostile or confused link: strangers, floods, a slow line.

Every flood here is bounded in count and time and stops by itself (a subprocess that exits
after FLOOD_S, or a loop with a fixed count); traffic stays on loopback. Assertions are on
behaviour (bytes, frames, counters, sim time); the wall-clock limits only make a broken
server fail instead of hang. The one ratio of sim time to wall time (the physics keeps real
time under a flood) has a wide margin because the machine is shared.
"""

from __future__ import annotations

import os
import select
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from protocol import DeviceID, Packet, PacketDecoder, PacketID, commands
from reach_sim_bridge.emulator.server import (
    TURNAROUND_BYTES,
    SimConfig,
    SimServer,
    out_frame_max_age,
    out_queue_limit,
)
from reach_sim_bridge.emulator.wire import OUT_QUEUE_S

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
    left = b""  # the rest of a short write: written first, so frames stay whole
    for _ in range(count):
        if time.monotonic() >= end and not left:
            break
        try:  # read the replies too, so the arm's writes succeed (the costly case)
            while os.read(fd, 65536):
                pass
        except BlockingIOError:
            pass
        try:
            data = left or chunk
            n = os.write(fd, data)
            sent, left = sent + n, data[n:]
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


# -- hole 2: the reply queue at --baud -------------------------------------------------------
class PtyReader:
    """Reads the pty continuously (a client keeping up with the line), keeping the packets.
    A plain descriptor: a flooder may share the pty (and read some of the replies)."""

    def __init__(self, srv: SimServer) -> None:
        assert srv.pty_path is not None
        self.srv = srv
        self.fd = os.open(srv.pty_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self.decoder = PacketDecoder()
        self.packets: list[Packet] = []

    def poll(self, timeout: float = 0.01) -> None:
        select.select([self.fd], [], [], timeout)
        try:
            data = os.read(self.fd, 65536)
        except BlockingIOError:
            return
        self.packets += self.decoder.feed(data)

    def send(self, *packets: Packet) -> None:
        data = b"".join(p.encode() for p in packets)
        deadline = time.monotonic() + WALL_LIMIT_S
        while data:
            assert time.monotonic() < deadline, "the pty never took our bytes"
            try:
                data = data[os.write(self.fd, data) :]
            except BlockingIOError:
                self.poll()

    def read_for(self, wall_s: float) -> None:
        end = time.monotonic() + wall_s
        while time.monotonic() < end:
            self.poll()

    def until(self, key: tuple[int, int], start: int) -> tuple[int, float]:
        """Read until a packet with `key` arrives after index `start`: its index and the sim
        time it arrived at."""
        deadline = time.monotonic() + WALL_LIMIT_S
        while True:
            for i in range(start, len(self.packets)):
                if self.packets[i].key == key:
                    return i, self.srv.sim_time
            start = len(self.packets)
            assert time.monotonic() < deadline, f"no {key} within {WALL_LIMIT_S} s"
            self.poll()

    def quiet(self, wall_s: float = 0.3) -> None:
        """Read until nothing arrived for `wall_s` (bounded by WALL_LIMIT_S)."""
        deadline = time.monotonic() + WALL_LIMIT_S
        last = len(self.packets)
        idle_since = time.monotonic()
        while time.monotonic() - idle_since < wall_s:
            assert time.monotonic() < deadline, "the line never went quiet"
            self.poll()
            if len(self.packets) != last:
                last, idle_since = len(self.packets), time.monotonic()

    def close(self) -> None:
        os.close(self.fd)


def test_heartbeat_overload_at_baud_is_dropped_oldest_first_and_replies_go_first() -> None:
    baud = 115200
    limit = out_queue_limit(baud)
    with SimServer(SimConfig(speed=1.0, baud=baud)) as srv:
        reader = PtyReader(srv)
        try:
            # 5 devices x 3 ids x 255 Hz: over three times what 115200 baud carries.
            reader.send(
                commands.heartbeat_set(BROADCAST, HEARTBEAT_IDS),
                commands.heartbeat_frequency(BROADCAST, 255),
            )
            reader.read_for(1.5)
            assert beats(reader.packets) > 100
            # A request is answered ahead of the stale stream: within the queue's wire time
            # (plus the request's own crossing), not after everything queued so far.
            mark = len(reader.packets)
            asked = srv.sim_time
            reader.send(commands.request(B, [PacketID.SERIAL_NUMBER]))
            _, answered = reader.until((B, PacketID.SERIAL_NUMBER), mark)
            assert answered - asked < 0.5
            # Switched off, the stream stops after at most a queue's worth of stale frames.
            mark = len(reader.packets)
            reader.send(commands.heartbeat_frequency(BROADCAST, 0))
            reader.quiet()
            stale = len(reader.packets) - mark
            assert stale * 8 <= limit + 2 * 64, f"{stale} frames after the heartbeat stopped"
            stats = srv.stats()
            print(f"answered in {answered - asked:.3f} s, {stale} stale frames, {stats}")
            assert stats.stream_dropped > 0
            assert stats.queued_peak_bytes <= limit
            assert reader.decoder.stats.bad_total == 0  # drops are whole frames
        finally:
            reader.close()
        assert srv.error is None


def test_request_flood_at_baud_keeps_the_queue_bounded_and_answers_after_it() -> None:
    baud = 115200
    limit = out_queue_limit(baud)
    # 7 bytes asking for 5 replies of 10: the answers need seven times the line's rate.
    ask_positions = commands.request(BROADCAST, [PacketID.POSITION]).encode()
    with SimServer(SimConfig(speed=1.0, baud=baud)) as srv:
        assert srv.pty_path is not None
        reader = PtyReader(srv)
        try:
            flood = start_flood("pty", srv.pty_path, ask_positions * 64)
            while flood.poll() is None:
                reader.poll()
            sent = finish_flood(flood)
            assert sent > 0
            deadline = time.monotonic() + WALL_LIMIT_S
            while srv.stats().bytes_in < sent:  # the tty's backlog (about 17 kB)
                assert time.monotonic() < deadline
                reader.poll()
            reader.quiet()  # the last of it answered (or dropped): no endless backlog
            mark = len(reader.packets)
            asked = srv.sim_time
            reader.send(commands.request(C, [PacketID.POSITION_LIMITS]))  # not in the flood
            _, answered = reader.until((C, PacketID.POSITION_LIMITS), mark)
            assert answered - asked < 0.5
            stats = srv.stats()
            print(f"probe answered after {answered - asked:.3f} s; sent {sent}; {stats}")
            assert stats.queued_peak_bytes <= limit
            assert stats.replies_dropped > 0
        finally:
            reader.close()
        assert srv.error is None


class VirtualLine:
    """The --baud line of a server that is not started, driven on a virtual clock: host
    bytes arrive when told, the arm acts on them as they land (no physics), and the frames it
    puts on the line are kept with the time their last byte lands. Exact and independent of
    the host's load, for bounds in line time."""

    def __init__(self, **config: object) -> None:
        self.srv = SimServer(SimConfig(**config))  # type: ignore[arg-type]
        self.now = 0.0
        self.out: list[tuple[float, Packet]] = []
        self._wire: tuple[float, bytes] | None = None

    def send(self, *packets: Packet) -> None:
        self.srv._arrive(b"".join(p.encode() for p in packets), self.now)

    def run(self, until: float, step: float = 0.0002) -> None:
        srv = self.srv
        while self.now < until:
            srv._earn(step)
            srv._take_input(self.now)
            while True:  # as the server's flush: one frame on the line at a time
                if self._wire is None:
                    self._wire = srv._pty_next(self.now)
                    if self._wire is None:
                        break
                landed, frame = self._wire
                if landed > self.now:
                    break
                self.out.append((landed, PacketDecoder().feed(frame)[0]))
                self._wire = None
            self.now += step

    @property
    def host_done(self) -> float:
        """When the host's last byte has landed."""
        return self.srv._rx_free


def test_a_reply_held_back_by_a_half_duplex_host_too_long_is_dropped_not_sent_stale() -> None:
    """The reply queue is bounded in time, not only in bytes: on a half-duplex wire the arm
    cannot talk while the host does, so a host that keeps the line 0.6 s left its replies
    queued (330 bytes, well inside the byte bound) and sent them 0.6 s stale, ahead of the
    answer to its next request. Older than out_frame_max_age (0.4 s at 115200) they are
    dropped and counted, and the next request is answered as soon as the wire is the arm's:
    the turnaround and the reply's own bytes."""
    baud = 115200
    line = VirtualLine(baud=baud, half_duplex=True)
    stale = [commands.request(E, [PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT])] * 10
    nobody = commands.request(DeviceID.F, [PacketID.POSITION])  # no such device: no reply
    filler = [nobody] * int(0.6 * baud / 10 / len(nobody.encode()))
    probe = commands.request(C, [PacketID.POSITION_LIMITS])
    line.send(*stale, *filler, probe)
    line.run(line.host_done + 0.1)
    assert line.out, "nothing was answered"
    first_t, first = line.out[0]
    assert first.key == (C, PacketID.POSITION_LIMITS), [p for _, p in line.out[:3]]
    assert len(line.out) == 1
    reply_s = (TURNAROUND_BYTES + len(first.encode())) * 10 / baud
    assert first_t - line.host_done == pytest.approx(reply_s, abs=0.001)
    assert line.srv.stats().replies_dropped == 30
    assert out_frame_max_age(baud) == pytest.approx(0.4, abs=0.001)


def test_after_broadcast_requests_at_half_the_line_rate_the_next_request_is_answered() -> None:
    """Issue 46's case: broadcast POSITION requests at half of a 115200 baud line for 2 s
    (each asks five replies, 3.5 times what the line carries back) left the next request
    unanswered for over 3 s. The queue holds OUT_QUEUE_S of wire time and drops the
    oldest, so the next request is answered within that (plus its own bytes)."""
    baud = 115200
    line = VirtualLine(baud=baud)
    ask = commands.request(BROADCAST, [PacketID.POSITION])
    every = 2 * len(ask.encode()) * 10 / baud  # half the line's rate
    while line.now < 2.0:
        line.send(ask)
        line.run(line.now + every)
    asked = line.now
    probe = commands.request(C, [PacketID.POSITION_LIMITS])
    line.send(probe)
    line.run(asked + 1.0)
    answered = [t for t, p in line.out if p.key == (C, PacketID.POSITION_LIMITS)]
    assert answered, "the request after the flood was never answered"
    assert answered[0] - asked <= OUT_QUEUE_S + 0.01
    stats = line.srv.stats()
    assert stats.replies_dropped > 0
    assert stats.queued_peak_bytes <= out_queue_limit(baud)


# -- hole 3: a flood and the physics ---------------------------------------------------------
@pytest.mark.parametrize("kind", ["pty", "udp"])
def test_a_request_flood_does_not_starve_the_physics(kind: str) -> None:
    with SimServer(SimConfig(speed=1.0, pty=kind == "pty", udp=("127.0.0.1", 0))) as srv:
        if kind == "pty":
            assert srv.pty_path is not None
            target, chunk = srv.pty_path, ASK_ALL * 240
            # Keep the slave open so the arm's replies fill the pty buffer and are lost
            # rather than erroring; the flooder writes through its own descriptor.
            holder = os.open(target, os.O_RDWR | os.O_NOCTTY)
        else:
            host, port = srv.udp_address or ("", 0)
            target, chunk = f"{host}:{port}", ASK_ALL * (65000 // len(ASK_ALL))
            holder = -1
        try:
            flood = start_flood(kind, target, chunk)
            deadline = time.monotonic() + WALL_LIMIT_S
            while srv.stats().bytes_in == 0:
                assert time.monotonic() < deadline and flood.poll() is None
                time.sleep(0.005)
            wall0, sim0 = time.monotonic(), srv.sim_time
            finish_flood(flood)
            wall1, sim1 = time.monotonic(), srv.sim_time
            ratio = (sim1 - sim0) / (wall1 - wall0)
            print(f"{kind}: sim/wall {ratio:.2f} over {wall1 - wall0:.2f} s, {srv.stats()}")
            assert ratio > 0.8, f"sim time advanced {ratio:.2f} x wall time under the flood"
            assert wall1 - wall0 > 0.5 * FLOOD_S
            # The arm still answers once the flood is over.
            probe = udp_socket() if kind == "udp" else None
            if probe is not None:
                srv.wait_sim_time(srv.sim_time + 0.5, timeout=WALL_LIMIT_S)
                udp_packets(probe)
                assert srv.udp_address is not None
                probe.sendto(commands.request(D, [PacketID.DEVICE_ID]).encode(), srv.udp_address)
                got = udp_collect(probe, srv, 1.0)
                probe.close()
                assert Packet(D, PacketID.DEVICE_ID, b"\x04") in got
        finally:
            if holder >= 0:
                os.close(holder)
        assert srv.error is None


def test_stop_returns_while_a_flood_goes_on() -> None:
    srv = SimServer(SimConfig(speed=1.0, pty=False, udp=("127.0.0.1", 0)))
    srv.start()
    host, port = srv.udp_address or ("", 0)
    flood = start_flood("udp", f"{host}:{port}", ASK_ALL)
    try:
        deadline = time.monotonic() + WALL_LIMIT_S
        while srv.stats().datagrams_in == 0:
            assert time.monotonic() < deadline and flood.poll() is None
            time.sleep(0.005)
        srv.stop()  # acts on a bounded last burst, not on the flood until it ends
        assert flood.poll() is None, "stop() waited for the flood to end"
    finally:
        srv.stop()
        finish_flood(flood)
    assert srv.error is None
