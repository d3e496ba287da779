"""reach-sim's half duplex (`SimConfig(half_duplex=True)`, `--half-duplex`): the pty as one
RS-485 wire. The arm waits for the host's bytes to land and a turnaround before it talks;
host bytes sent while it talks collide and both frames are lost, counted (docs/protocol.md
section 9; the model is in reach_sim_bridge/emulator/server.py's docstring)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import serial

from protocol import DeviceID, Packet, PacketDecoder, PacketID, commands
from reach_driver import ArmClient, open_transport
from reach_sim_bridge.cli import build_parser, config_from_args
from reach_sim_bridge.emulator.server import TURNAROUND_BYTES, SimConfig, SimServer

E, D = DeviceID.E, DeviceID.D
#: Ten ids E answers in one go: ten frames back to back on the wire.
TEN_IDS = [
    PacketID.POSITION,
    PacketID.VELOCITY,
    PacketID.CURRENT,
    PacketID.MODE,
    PacketID.POSITION_LIMITS,
    PacketID.VELOCITY_LIMITS,
    PacketID.CURRENT_LIMITS,
    PacketID.SOFTWARE_VERSION,
    PacketID.SERIAL_NUMBER,
    PacketID.MODEL_NUMBER,
]


def byte_s(baud: int) -> float:
    return 10.0 / baud  # 8N1


@pytest.fixture
def serve() -> Iterator:
    servers: list[SimServer] = []

    def start(**kw: object) -> SimServer:
        server = SimServer(SimConfig(**kw))  # type: ignore[arg-type]
        server.start()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.stop()
        assert server.error is None


def _open(server: SimServer) -> serial.Serial:
    assert server.pty_path is not None
    return serial.Serial(server.pty_path, 115200, timeout=0.0)


def _read_until(port: serial.Serial, n: int, timeout: float) -> tuple[list[Packet], float]:
    """At least `n` packets (or what came by `timeout`) and when the first one arrived."""
    decoder = PacketDecoder()
    got: list[Packet] = []
    first = float("nan")
    end = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < end:
        data = port.read(port.in_waiting or 1)
        if data:
            packets = decoder.feed(data)
            if packets and not got:
                first = time.monotonic()
            got += packets
        else:
            time.sleep(0.0005)
    return got, first


def _reply_delay(server: SimServer, idle_bytes: int) -> float:
    """Seconds from writing a REQUEST followed by `idle_bytes` stray delimiters (bytes on the
    wire that ask nothing) to its answer."""
    port = _open(server)
    try:
        sent = time.monotonic()
        port.write(commands.request(E, [PacketID.POSITION]).encode() + bytes(idle_bytes))
        got, first = _read_until(port, 1, timeout=20.0)
    finally:
        port.close()
    assert [p.key for p in got] == [(E, PacketID.POSITION)]
    return first - sent


def test_the_arm_does_not_talk_while_host_bytes_are_arriving(serve) -> None:
    # 800 byte times at 9600 baud: 0.83 s of the host's bytes, long enough that full duplex's
    # answer beats them even when a loaded host reads it a few hundred ms late
    baud, idle = 9600, 800
    request = len(commands.request(E, [PacketID.POSITION]).encode())
    half = _reply_delay(serve(baud=baud, half_duplex=True), idle)
    # The host's bytes all land, the line stays quiet TURNAROUND_BYTES, then the 10-byte reply.
    assert half >= (request + idle + TURNAROUND_BYTES + 10) * byte_s(baud)
    # Full duplex at the same baud answers on the other wire, while the zeros still arrive.
    full = _reply_delay(serve(baud=baud), idle)
    assert full < (request + idle) * byte_s(baud) < half


def test_talking_over_the_arm_collides_and_is_counted(serve) -> None:
    # Ten replies take ~1.2 s of wire at 1200 baud: time to talk over them even when a loaded
    # host runs this thread a few hundred ms late after the first one.
    baud = 1200
    server = serve(baud=baud, half_duplex=True)
    port = _open(server)
    try:
        port.write(commands.request(E, TEN_IDS).encode())
        got, _ = _read_until(port, 1, timeout=20.0)  # the first reply is out: the arm talks on
        port.write(commands.request(D, [PacketID.SOFTWARE_VERSION]).encode())
        # the other nine but the one garbled (a deadline), then a look for any more
        more, _ = _read_until(port, len(TEN_IDS) - 2, timeout=20.0)
        more += _read_until(port, 1, timeout=0.5)[0]
    finally:
        port.close()
    got += more
    stats = server.stats()
    assert stats.collisions == 1  # the host's REQUEST to D
    assert stats.collided_out == 1  # the arm's frame it garbled on the wire
    assert stats.collision_bytes == len(commands.request(D, [PacketID.SOFTWARE_VERSION]).encode())
    keys = [p.key for p in got]
    assert (D, PacketID.SOFTWARE_VERSION) not in keys  # never reached the arm
    assert len(keys) == len(TEN_IDS) - 1 and set(keys) < {(E, p) for p in TEN_IDS}
    assert keys[0] == (E, PacketID.POSITION)
    assert stats.bad_frames == {} and stats.firmware_errors == {}


def test_a_well_behaved_half_duplex_client_gets_every_answer(serve) -> None:
    """The driver's RS-485 transport (write, wait for the answer, a quiet gap) through the
    half-duplex arm: discovery, limits, polls and diagnostics with no collision."""
    server = serve(baud=115200, half_duplex=True, link=None)
    assert server.pty_path is not None
    with ArmClient(open_transport(server.pty_path, rs485=True)).start() as client:
        assert set(client.found_devices) == {1, 2, 3, 4, 5}
        for _ in range(40):
            state = client.read_joints((PacketID.POSITION, PacketID.VELOCITY))
            assert all(v == v for v in state.q)  # no NaN: every joint answered
        diag = client.read_diagnostics()
        timeouts = client.stats.request_timeouts
    stats = server.stats()
    assert all(js.voltage is not None for js in diag.values())
    assert stats.collisions == 0 and stats.collided_out == 0, stats
    assert timeouts == 0
    assert stats.bad_frames == {} and stats.firmware_errors == {}
    assert stats.frames_out >= 40 * 8


def test_broadcast_requests_collide_on_the_half_duplex_arm(serve) -> None:
    server = serve(baud=115200, half_duplex=True)
    port = _open(server)
    try:
        port.write(commands.request(DeviceID.BROADCAST, [PacketID.POSITION]).encode())
        got, _ = _read_until(port, 1, timeout=0.5)
    finally:
        port.close()
    assert got == []
    assert server.stats().ignored.get("broadcast_collision") == 1


def test_half_duplex_needs_the_pty_and_a_baud_and_the_cli_defaults_it() -> None:
    with pytest.raises(ValueError, match="needs the pty and its baud"):
        SimConfig(half_duplex=True)
    with pytest.raises(ValueError, match="needs the pty and its baud"):
        SimConfig(half_duplex=True, baud=115200, pty=False, udp=("127.0.0.1", 0))
    config = config_from_args(build_parser().parse_args(["--half-duplex"]))
    assert config.half_duplex and config.baud == 115200
    config = config_from_args(build_parser().parse_args(["--half-duplex", "--baud", "9600"]))
    assert config.baud == 9600
    assert not config_from_args(build_parser().parse_args([])).half_duplex
    assert "--half-duplex" in build_parser().format_help()
