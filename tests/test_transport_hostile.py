"""The serial transport against what a shared line does to it: a second driver on the same
port, and a partial frame left on the line by a previous host.

Ptys stand in for the arm's serial port (`os.openpty()`, or the virtual arm's own pty).
"""

from __future__ import annotations

import os
import subprocess
import sys
import termios
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import wait_until

from protocol import DeviceID, Packet, PacketDecoder, PacketID, commands
from reach_driver import ArmClient, LinkConfig, TransportError, open_transport
from reach_driver.errors import PortBusyError

ROOT = Path(__file__).resolve().parents[1]
E = DeviceID.E


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    """(master fd, slave path) of a raw pty; the slave is kept open as a real port's node."""
    master, slave = os.openpty()
    tty.setraw(slave, termios.TCSANOW)
    os.set_blocking(master, False)
    path = os.ttyname(slave)
    yield master, path
    os.close(master)
    os.close(slave)


def master_read(master: int, want: int, timeout: float = 20.0) -> bytes:
    """`want` bytes from the pty's master side, or what came by `timeout` (a deadline)."""
    out = b""
    end = time.monotonic() + timeout
    while len(out) < want and time.monotonic() < end:
        try:
            out += os.read(master, 4096)
        except BlockingIOError:
            time.sleep(0.002)
    return out


def read_for(t, seconds: float) -> bytes:
    out = b""
    end = time.monotonic() + seconds
    while True:  # past the deadline, until a read finds nothing: a host pause eats no data
        chunk = t.read()
        out += chunk
        if not chunk and time.monotonic() >= end:
            return out


# -- one port, one driver ----------------------------------------------------------------------


def test_a_second_open_of_a_held_pty_is_refused_and_the_first_keeps_working(pty) -> None:
    master, path = pty
    first = open_transport(path)
    try:
        master_read(master, 1, timeout=0.1)  # whatever the first wrote on open
        with pytest.raises(PortBusyError, match=rf"{path} is in use.*pid {os.getpid()}\b"):
            open_transport(path)
        assert isinstance(PortBusyError("x"), TransportError)
        # Both directions of the first are untouched by the refused open.
        frame = commands.position(E, 1.5).encode()
        first.write(frame)
        assert master_read(master, len(frame)) == frame
        reply = commands.velocity(E, 0.25).encode()
        os.write(master, reply)
        assert read_for(first, 0.1) == reply
    finally:
        first.close()
    # Once the first lets go, the port opens again.
    again = open_transport(path)
    again.close()


def test_a_port_held_by_another_process_names_its_pid_and_command(pty) -> None:
    _, path = pty
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from reach_driver import open_transport; "
            "t = open_transport(sys.argv[1]); print('held', flush=True); time.sleep(30)",
            path,
        ],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(PortBusyError) as info:
            open_transport(path)
        message = str(info.value)
        assert f"{path} is in use" in message
        assert f"pid {holder.pid}" in message and "open_transport" in message
    finally:
        holder.kill()
        holder.wait(5)


def test_a_second_driver_on_the_virtual_arm_leaves_the_first_answering(sim) -> None:
    link = str(sim.link)
    with ArmClient(open_transport(link), link=LinkConfig(reconnect=False)) as arm:
        arm.request(E, [PacketID.POSITION])
        with pytest.raises(PortBusyError, match="is in use"):
            open_transport(link)
        for _ in range(5):
            assert PacketID.POSITION in arm.request(E, [PacketID.POSITION], retries=0)


# -- a clean start on a dirty line -------------------------------------------------------------


def test_the_first_byte_after_open_is_a_delimiter_on_loop() -> None:
    t = open_transport("loop://")
    try:
        frame = commands.position(E, 1.5).encode()
        t.write(frame)
        assert read_for(t, 0.05) == b"\x00" + frame
    finally:
        t.close()


def test_the_first_byte_after_open_is_a_delimiter_on_a_pty(pty) -> None:
    master, path = pty
    t = open_transport(path)
    try:
        assert master_read(master, 1) == b"\x00"
        frame = commands.request(E, [PacketID.POSITION]).encode()
        t.write(frame)
        assert master_read(master, len(frame)) == frame
    finally:
        t.close()
    t.open()  # every open, reconnects included
    try:
        assert master_read(master, 1) == b"\x00"
    finally:
        t.close()


def test_a_request_after_a_stray_partial_frame_is_answered_at_once(sim) -> None:
    link = str(sim.link)
    # A previous host died mid-frame: 6 bytes of a POSITION command and no delimiter.
    stray = commands.position(E, 2.0).encode()[:6]
    fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
    try:
        before = sim.stats().bytes_in
        os.write(fd, stray)
        assert wait_until(lambda: sim.stats().bytes_in >= before + len(stray), timeout=2.0)
    finally:
        os.close(fd)
    t = open_transport(link)
    try:
        t.write(commands.request(E, [PacketID.POSITION]).encode())  # once: no retry
        decoder = PacketDecoder()
        got: list[Packet] = []
        end = time.monotonic() + 20.0  # a deadline: the answer comes within milliseconds
        while not got and time.monotonic() < end:
            got = [
                p
                for p in decoder.feed(t.read())
                if p.device_id == E and p.packet_id == PacketID.POSITION
            ]
        assert got, "the request was swallowed by the stray partial frame"
    finally:
        t.close()


def test_the_can_tunnel_also_opens_with_a_delimiter() -> None:
    from reach_driver.transport_can import CanTransport, CanTunnelConfig

    ch = f"hostile-{os.getpid()}-{time.monotonic_ns()}"
    gateway = CanTransport("virtual", ch, CanTunnelConfig().swapped())
    gateway.open()
    try:
        host = open_transport(f"can://virtual/{ch}")
        try:
            assert read_for(gateway, 0.1).startswith(b"\x00")
        finally:
            host.close()
    finally:
        gateway.close()


def test_udp_sends_nothing_on_open() -> None:
    import socket

    arm = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    arm.bind(("127.0.0.1", 0))
    arm.settimeout(0.1)
    try:
        host, port = arm.getsockname()
        t = open_transport(f"udp://{host}:{port}")
        try:
            with pytest.raises(TimeoutError):
                arm.recvfrom(100)  # datagrams leave no partial frame: nothing to clear
        finally:
            t.close()
    finally:
        arm.close()
