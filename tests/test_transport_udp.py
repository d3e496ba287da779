"""UDP transport against a plain socket standing in for the arm."""

from __future__ import annotations

import socket
import time
from typing import cast

import pytest

from protocol import Mode, PacketDecoder, commands
from reach_driver import BadUrlError, open_transport
from reach_driver.transport_udp import MAX_DATAGRAM, UdpTransport


@pytest.fixture
def arm_socket():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(1.0)
    yield sock
    sock.close()


def read_for(t, seconds: float = 0.1) -> bytes:
    out = b""
    end = time.monotonic() + seconds
    while True:  # past the deadline, until a read finds nothing: a host pause eats no data
        chunk = t.read()
        out += chunk
        if not chunk and time.monotonic() >= end:
            return out


def test_url_parsing_defaults_to_port_6789() -> None:
    t = open_transport("udp://192.168.2.3", open_now=False)
    assert isinstance(t, UdpTransport)
    assert (t.host, t.port) == ("192.168.2.3", 6789)
    t6 = cast(UdpTransport, open_transport("udp://[::1]:7000", open_now=False))
    assert (t6.host, t6.port) == ("::1", 7000)


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("udp://:7000", "no host"),
        ("udp://host:notaport", "bad port"),
        ("udp://host:7000/path", "unexpected path"),
        ("udp://host:99999", "bad port"),
    ],
)
def test_bad_udp_urls_say_what_is_wrong(url: str, message: str) -> None:
    with pytest.raises(BadUrlError, match=message):
        open_transport(url, open_now=False)


def test_serial_options_are_refused_for_udp() -> None:
    with pytest.raises(BadUrlError, match="--rs485 applies to serial"):
        open_transport("udp://127.0.0.1", rs485=True)
    with pytest.raises(BadUrlError, match="--baud applies to serial"):
        open_transport("udp://127.0.0.1", baud=9600)


def test_several_frames_per_datagram_both_ways(arm_socket) -> None:
    host, port = arm_socket.getsockname()
    t = cast(UdpTransport, open_transport(f"udp://{host}:{port}"))
    frames = [commands.request(d, [3, 2]).encode() for d in (5, 4, 3, 2)]
    t.write_frames(frames)
    data, source = arm_socket.recvfrom(65535)
    assert data == b"".join(frames)  # one datagram
    assert source[1] == t.local_address[1]
    replies = [
        commands.position(5, 1.0),
        commands.velocity(5, 0.5),
        commands.mode(4, Mode.POSITION),
    ]
    arm_socket.sendto(b"".join(p.encode() for p in replies), source)
    assert PacketDecoder().feed(read_for(t)) == replies
    t.close()


def test_datagrams_from_other_sources_are_dropped_and_counted(arm_socket) -> None:
    host, port = arm_socket.getsockname()
    t = open_transport(f"udp://{host}:{port}")
    t.write(commands.request(5, [3]).encode())
    _, me = arm_socket.recvfrom(65535)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
        stranger.sendto(commands.position(5, 9.0).encode(), me)
        time.sleep(0.02)
        arm_socket.sendto(commands.position(5, 1.0).encode(), me)
        got = PacketDecoder().feed(read_for(t))
    assert got == [commands.position(5, 1.0)]
    assert t.stats.foreign_datagrams == 1
    t.close()


def test_a_truncated_datagram_cannot_glue_onto_the_next(arm_socket) -> None:
    host, port = arm_socket.getsockname()
    t = open_transport(f"udp://{host}:{port}")
    t.write(b"\x00")
    _, me = arm_socket.recvfrom(65535)
    good = commands.position(4, 2.0).encode()
    arm_socket.sendto(good[:-3], me)  # a frame cut short, no delimiter
    arm_socket.sendto(good, me)
    dec = PacketDecoder()
    assert dec.feed(read_for(t)) == [commands.position(4, 2.0)]
    assert dec.stats.bad_total == 1
    t.close()


def test_long_batches_split_on_frame_boundaries(arm_socket) -> None:
    host, port = arm_socket.getsockname()
    t = open_transport(f"udp://{host}:{port}")
    frames = [commands.current(d % 5 + 1, float(i)).encode() for i, d in enumerate(range(300))]
    t.write_frames(frames)
    datagrams: list[bytes] = []
    while sum(map(len, datagrams)) < sum(map(len, frames)):
        datagrams.append(arm_socket.recv(65535))
    assert len(datagrams) > 1
    assert all(len(d) <= MAX_DATAGRAM and d.endswith(b"\x00") for d in datagrams)
    dec = PacketDecoder()
    assert [p.encode() for d in datagrams for p in dec.feed(d)] == frames
    t.close()


def test_unknown_host_is_a_transport_error() -> None:
    from reach_driver import TransportError

    with pytest.raises(TransportError, match="cannot resolve"):
        open_transport("udp://no-such-host.invalid")
