"""RS-485 half duplex in the serial transport: the local echo of a two-wire adapter (each byte
written comes back on the receive line) is dropped, the arm's own bytes are kept, and the
wire budget is the shared line's. A raw pty stands in for the adapter; a thread on its master
side plays the adapter's echo and the arm."""

from __future__ import annotations

import os
import termios
import threading
import time
import tty
from collections.abc import Iterator

import pytest

from protocol import DeviceID, PacketDecoder, PacketID, commands
from reach_driver.transport_serial import SerialTransport

E = DeviceID.E
REPLY = commands.position(E, 1.25).encode()  # what the "arm" answers (a POSITION)


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(slave, termios.TCSANOW)
    path = os.ttyname(slave)
    yield master, path
    os.close(master)
    os.close(slave)


class EchoingAdapter(threading.Thread):
    """Echoes every byte the host writes, then (if `answer`) sends the arm's REPLY."""

    def __init__(self, master: int, answer: bool = True) -> None:
        super().__init__(daemon=True)
        self.master, self.answer = master, answer
        self.stop = threading.Event()
        self.heard = b""

    def run(self) -> None:
        os.set_blocking(self.master, False)
        while not self.stop.is_set():
            try:
                data = os.read(self.master, 4096)
            except BlockingIOError:
                time.sleep(0.001)
                continue
            except OSError:
                return
            self.heard += data
            os.write(self.master, data)  # the adapter's local echo
            if self.answer and data.endswith(b"\x00") and data.strip(b"\x00"):
                time.sleep(0.003)  # the arm's turnaround
                os.write(self.master, REPLY)


def _read_for(t: SerialTransport, seconds: float) -> bytes:
    out = b""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out += t.read() or b""
    return out


def _read_until(t: SerialTransport, want: bytes, timeout: float = 20.0) -> bytes:
    """What the transport reads until `want` is in it (the reply, after any echo: the echo
    comes first on the wire), or `timeout` seconds pass: a deadline, not a window."""
    out = b""
    end = time.monotonic() + timeout
    while want not in out and time.monotonic() < end:
        out += t.read() or b""
    return out


def _exchange(path: str, master: int, *, rs485: bool) -> tuple[bytes, bytes]:
    adapter = EchoingAdapter(master)
    adapter.start()
    t = SerialTransport(path, rs485=rs485, read_timeout_s=0.01)
    t.open()
    try:
        request = commands.request(E, [PacketID.POSITION]).encode()
        t.write_frames([request])
        got = _read_until(t, REPLY)
    finally:
        t.close()
        adapter.stop.set()
        adapter.join()
    return request, got


def test_rs485_drops_the_local_echo_and_keeps_the_reply(pty) -> None:
    master, path = pty
    request, got = _exchange(path, master, rs485=True)
    assert request not in got
    packets = PacketDecoder().feed(got)
    assert [(p.device_id, p.packet_id, p.as_float()) for p in packets] == [
        (E, PacketID.POSITION, 1.25)
    ]


def test_without_rs485_the_echo_comes_through(pty) -> None:
    """What the suppression is for: on a full-duplex setting the echo reads as a frame."""
    master, path = pty
    request, got = _exchange(path, master, rs485=False)
    assert request in got
    packets = PacketDecoder().feed(got)
    assert PacketID.REQUEST in [p.packet_id for p in packets]


def test_an_adapter_that_does_not_echo_loses_nothing(pty) -> None:
    """No echo: the reply is never mistaken for one, even though it arrives where the echo
    was expected."""
    master, path = pty
    t = SerialTransport(path, rs485=True, read_timeout_s=0.01)
    t.open()
    try:
        t.write_frames([commands.request(E, [PacketID.POSITION]).encode()])
        os.write(master, REPLY)
        got = _read_until(t, REPLY)
    finally:
        t.close()
    assert got == REPLY
    assert t.echo_bytes_dropped == 0


def test_an_echo_split_across_reads_is_still_dropped(pty) -> None:
    master, path = pty
    t = SerialTransport(path, rs485=True, read_timeout_s=0.01)
    t.open()
    try:
        frames = [commands.request(E, [PacketID.POSITION]).encode(), commands.mode(E, 0).encode()]
        t.write_frames(frames)
        time.sleep(0.01)
        echo = os.read(master, 4096)  # the bytes on the wire (the open's 0x00, the frames)
        assert echo.endswith(b"".join(frames))
        got = b""
        for i in range(0, len(echo), 3):  # the echo trickles in, three bytes at a time
            os.write(master, echo[i : i + 3])
            got += _read_for(t, 0.02)
        os.write(master, REPLY)
        got += _read_until(t, REPLY)
    finally:
        t.close()
    assert got == REPLY
    assert t.echo_bytes_dropped == len(echo)


def test_rs485_budget_is_half_the_line() -> None:
    full = SerialTransport("loop://", baud=115200)
    half = SerialTransport("loop://", baud=115200, rs485=True)
    assert full.wire_bytes_per_s == pytest.approx(11520.0)
    assert half.wire_bytes_per_s == pytest.approx(11520.0 / 2)


def test_echoes_on_either_side_of_a_reply_are_all_dropped(pty) -> None:
    """echo 1, the arm's answer to frame 1, echo 2: the answer is not taken for a bad echo."""
    master, path = pty
    t = SerialTransport(path, rs485=True, read_timeout_s=0.01)
    t.open()
    try:
        first = commands.request(E, [PacketID.POSITION]).encode()
        second = commands.request(DeviceID.D, [PacketID.POSITION]).encode()
        t.write_frames([first, second])
        time.sleep(0.01)
        wire = os.read(master, 4096)  # the open's 0x00 and both frames
        os.write(master, wire[: -len(second)] + REPLY + second)
        got = _read_until(t, REPLY)
        got += _read_for(t, 0.1)  # and the second echo after it, dropped too
    finally:
        t.close()
    assert got == REPLY
    assert t.local_echo is True


def test_an_adapter_that_never_echoes_is_found_out(pty) -> None:
    master, path = pty
    t = SerialTransport(path, rs485=True, read_timeout_s=0.01)
    t.open()
    try:
        t.write_frames([commands.request(E, [PacketID.POSITION]).encode()] * 9)
        time.sleep(0.35)  # past every echo's window
        assert _read_for(t, 0.05) == b""
        assert t.local_echo is False
        os.write(master, REPLY)
        assert _read_until(t, REPLY) == REPLY
    finally:
        t.close()
